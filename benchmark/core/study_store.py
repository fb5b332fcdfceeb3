"""What a study keeps of the output it writes into: its earlier rows, merged with this run's.

Each study merges its rows into its table with the one merge (`benchmark.core.store.merge_rows`;
on the runner, `benchmark.core.study.run`: `MergedTable`), each table with its own row identity:

* `run`: ``runs.csv``, one row per (scene, integrator, setting), read by the runs table's own
  policy (`benchmark.runs.table.read_runs`: untrusted rows named and recomputed, a table that
  cannot be read whole salvaged rather than refused; `Study.read`);
* `stability`: ``stability.csv``, one row per (scene, integrator, kind);
* `speed`: the rows table beside its Markdown file (``lgvi_speed.csv`` beside
  ``lgvi_speed.md``), one row per (kind, method, right-hand side, scene, N);
* `xval`: ``cost.csv``, one row per (case, N, code), a job's rows replaced as a whole, with the
  tips beside it in ``tips.npz`` (`benchmark.studies.xval_output`);
* `answer`: ``search.csv`` and ``timing.csv``, each row checked by its digest
  (`benchmark.answer.answer`).

A study's table, figure and README are then written from the whole merged table, and an
interrupted study has already merged each finished row: it never drops a row it did not
recompute. An earlier table that cannot be read is refused before any work (overwriting it
would lose it), naming the file and what to do (the runs table's is copied aside and its
readable rows kept: its rows are hours of measurement).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from reelbench.benchmark.core import store
from reelbench.benchmark.core.report import Provenance, earlier_runs


def read_rows(path: Path, identity: tuple, text_columns: tuple = (), read: Callable | None = None,
              digest: tuple | None = None, log: Callable[[str], None] | None = None) -> list[dict]:
    """The rows of a study's earlier table ``path`` ([] when there is none); ValueError (before
    any work) when it cannot be read or lacks an identity column. ``text_columns``: columns
    that hold names ("" where a row has none, so identities compare equal after a round trip).
    ``read(df)``: the study's reading of the table as read (`Study.read_earlier`), applied first.
    ``digest``: the rows carry a digest leaving out these columns (`store.row_digest`); a row
    whose digest fails is left out, and ``log`` names how many."""
    import io

    import pandas as pd

    from reelbench.models.io import FileRefused, read_regular_file

    path = Path(path)
    if not path.exists():
        return []
    try:  # a regular file of a table's size, read once (as the runs table's is: `benchmark.runs.table.read_runs`)
        df = pd.read_csv(io.BytesIO(read_regular_file(path, store.MAX_TABLE_BYTES)))
    except (FileRefused, OSError, ValueError, pd.errors.ParserError) as exc:
        raise ValueError(f"{path} holds earlier rows but cannot be read ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:120] if str(exc) else ''}); this run would overwrite it: move "
                         "it away, or give another --out") from None
    if read is not None:
        df = read(df)
    missing = [c for c in identity if c not in df.columns]
    if missing:
        raise ValueError(f"{path} is not a table of this study (no column {', '.join(missing)}); this run would "
                         "overwrite it: move it away, or give another --out")
    for c in text_columns:
        if c in df:
            df[c] = df[c].astype(object).where(df[c].notna(), "").astype(str)
    rows = [{k: v for k, v in r.items()} for r in df.to_dict("records")]
    if digest is None:
        return rows
    good = [r for r in rows if store.digest_holds(r, digest)]
    if len(good) < len(rows) and log is not None:
        log(f"warning: {path}: {len(rows) - len(good)} row(s) fail their digest; they are recomputed")
    return good


class MergedTable(store.TableWriter):
    """A study's `store.TableWriter` whose table is the earlier rows of ``path`` with this run's
    in their place (``identity``): every write, the first finished row's included, keeps the rows
    this run does not recompute. ``earlier``: how many rows the file held; ``kept(rows)``: how
    many of them the merged table keeps as they were. The earlier rows are read by `read_rows`
    (``read_earlier``: `Study.read_earlier`), or by the study's own reading policy ``read(path,
    log)`` (`Study.read`: the runs table's). ``digest``: this run's rows are written with their
    digest, leaving out these columns (the earlier rows keep theirs, checked when they were read)."""

    def __init__(self, path, identity: tuple, to_frame: Callable, text_columns: tuple = (),
                 expand: Callable[[dict], list[dict]] | None = None, read_earlier: Callable | None = None,
                 read: Callable | None = None, digest: tuple | None = None,
                 log: Callable[[str], None] | None = None):
        self.identity, self.expand, self.digest = tuple(identity), expand, digest
        if read is not None:
            self.base = read(Path(path), log)
        else:
            self.base = read_rows(path, self.identity, text_columns, read_earlier, digest, log)
        super().__init__(path, lambda rows: to_frame(self.merged(rows)))
        self.earlier = len(self.base)

    def merged(self, rows: list[dict]) -> list[dict]:
        out = store.merge_rows(self.base, rows, identity=self.identity, expand=self.expand)
        if self.digest is None:
            return out
        earlier = {id(r) for r in self.base}
        return [r if id(r) in earlier else {**r, store.DIGEST_COLUMN: store.row_digest(r, self.digest)} for r in out]

    def kept(self, rows: list[dict]) -> int:
        mine = {store.identity_of(r, self.identity) for r in rows}
        return sum(1 for r in self.base if store.identity_of(r, self.identity) not in mine)

    def provenance(self, provenance: Provenance, rows: list[dict], header_of: Path) -> Provenance:
        """``provenance`` naming the earlier runs (from the header of ``header_of``) when the
        merged table keeps rows of theirs."""
        return provenance.merged_into(earlier_runs(header_of)) if self.kept(rows) else provenance

    def stop_note(self, wording) -> str:
        """What an interrupted study saved, for its one line, in its words (`study.Wording`)."""
        if not self.saved:
            return (f"no {wording.row} had finished; {self.path} is as it was ({self.earlier} row(s))" if self.earlier
                    else f"no {wording.row} had finished, nothing saved")
        return (f"{self.saved} finished {wording.row}(s) {wording.saved} {self.path}"
                + (" (its earlier rows that this run did not recompute are kept)" if self.earlier else ""))
