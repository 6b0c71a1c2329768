"""Console entry point of ``sim_node``: stop signals are caught before the heavy imports.

Importing rclpy, numba and the compiled kernels takes a second or more; a Ctrl-C in that time
must end the node as cleanly as one that arrives later (exit status 0, no traceback).
"""

import os
import signal
import sys
import threading


def main() -> int:
    stop = threading.Event()

    def request_stop(signum, frame) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, request_stop)
    # Python runs a handler when the main thread next runs Python, which a long compile in
    # native code (LLVM) puts off for seconds; a byte on this pipe marks the signal at once
    # for a thread that reads it (see sim_node.main)
    wakeup, marked = os.pipe()
    os.set_blocking(marked, False)
    signal.set_wakeup_fd(marked, warn_on_full_buffer=False)
    if stop.is_set():
        return 0
    from feeder_sim.ros import node as sim_node
    code = sim_node.main(stop=stop, wakeup_fd=wakeup)
    # the log is final: a signal that arrives while the interpreter shuts down (when Python
    # has put the default handlers back) must not turn a clean exit into a kill
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    return code


if __name__ == '__main__':
    sys.exit(main())
