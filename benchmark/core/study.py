"""What every study shares when it writes into a directory: one writer at a time, and a stop
(Ctrl-C or SIGTERM) that ends the study with what it has saved."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable

from benchmark.core import engine
from benchmark.core import store


@contextlib.contextmanager
def exclusive(out: Path, log: Callable[[str], None]):
    """Hold ``out``'s lock, with Ctrl-C and SIGTERM both stopping the study (KeyboardInterrupt)."""
    with store.OutputLock(out, log=log):
        engine.install_stop_handlers()
        yield
