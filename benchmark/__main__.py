import signal
import sys


def _stop_early(signum, frame):
    # Until the command line installs its own handlers (benchmark.core.engine.install_stop_handlers),
    # a stop in the imports is one line too: Ctrl-C printed a traceback, SIGTERM nothing at all.
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")


def _send_again(unraisable):
    # A stop raised where Python drops exceptions (an import lock's callback, a finalizer) is
    # printed as "Exception ignored" and lost: send it again, to land in a frame that raises it.
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        import os
        import threading

        signum = signal.SIGTERM if "SIGTERM" in str(unraisable.exc_value) else signal.SIGINT
        # later, from a thread: raised here, inside the hook, it would be dropped again
        timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
        timer.daemon = True
        timer.start()
    else:
        sys.__unraisablehook__(unraisable)


signal.signal(signal.SIGINT, _stop_early)
signal.signal(signal.SIGTERM, _stop_early)
sys.unraisablehook = _send_again
try:
    from reelbench.benchmark.cli.main import main
except KeyboardInterrupt as exc:
    term = "SIGTERM" in str(exc)
    print(f"stopped by {'SIGTERM' if term else 'Ctrl-C'}: nothing was written (it had not started)", file=sys.stderr)
    sys.exit(143 if term else 130)

sys.exit(main())
