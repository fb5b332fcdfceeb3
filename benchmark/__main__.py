import signal
import sys


def _stop_early(signum, frame):
    # Until the command line installs its own handlers (benchmark.core.engine.install_stop_handlers),
    # a stop in the imports is one line too: Ctrl-C printed a traceback, SIGTERM nothing at all.
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")


signal.signal(signal.SIGINT, _stop_early)
signal.signal(signal.SIGTERM, _stop_early)
try:
    from benchmark.cli.main import main
except KeyboardInterrupt as exc:
    term = "SIGTERM" in str(exc)
    print(f"stopped by {'SIGTERM' if term else 'Ctrl-C'}: nothing was written (it had not started)", file=sys.stderr)
    sys.exit(143 if term else 130)

sys.exit(main())
