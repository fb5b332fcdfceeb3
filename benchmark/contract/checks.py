"""What the plugin contract's checks share (`benchmark.contract.integrator`,
`benchmark.contract.effect`): a `Check` per rule, the `ContractError` naming every failed one,
running a list of checks (`run_checks`), and the small scene both are checked on (`small_scene`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

#: the string's elements in the contract's small scenes
ELEMENTS = 3


@dataclass(frozen=True)
class Check:
    """One rule of the contract: its name, whether it holds, and the figure it was judged by."""

    name: str
    ok: bool
    figure: str

    def line(self) -> str:
        return f"{'ok  ' if self.ok else 'FAIL'}  {self.name}: {self.figure}"


class ContractError(AssertionError):
    """Raised by `check_integrator` / `check_effect` when a check fails; ``checks`` holds all of them."""

    def __init__(self, what: str, checks: list[Check]):
        self.checks = checks
        failed = [c for c in checks if not c.ok]
        super().__init__(f"{what} fails {len(failed)} of {len(checks)} checks:\n"
                         + "\n".join(c.line() for c in failed))


def run_checks(steps: list[tuple[str, Callable]], log) -> list[Check]:
    """Run each (name, check) in turn; a check that raises fails with the exception as its figure."""
    import time

    out = []
    for name, fn in steps:
        t0 = time.perf_counter()
        try:
            got = fn()
        except Exception as exc:  # a broken hook is a failed check, not a crash of verify
            got = [Check(name, False, f"raised {type(exc).__name__}: {str(exc).splitlines()[0][:300] if str(exc) else ''}")]
        seconds = time.perf_counter() - t0
        for c in got if isinstance(got, list) else [got]:
            out.append(c)
            if log:
                log(f"{c.line()} ({seconds:.1f} s)")
    return out


def small_scene(effects, elements: int = ELEMENTS, **overrides):
    """The retrieval scene reduced to ``effects`` (values adjusted to stay valid): a short,
    small scene that moves every coordinate."""
    from reelbench.models import load_scene

    kw = dict(effects=list(effects), elements=elements, tip_velocity=[0.3, 1.0, -0.2], reel_rate=0.0,
              angular_velocity=[0.4, -0.3, 0.8] if "rigid_body" in effects else [0.0, 0.0, 0.0])
    if "reel_control" not in effects:
        kw["control_moment"] = 0.0
    if "reel" in effects:
        kw["reel_rate"] = -0.7
    kw.update(overrides)
    return load_scene("retrieval", **kw)
