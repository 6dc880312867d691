"""The local fork server's last preload: freeze what the preloads made; exit without teardown.

Every ``LocalPool`` and ``start_fork_server`` list this module after their own preloads, so it
is imported once, in the fork server, after torch, MuJoCo and the video writer.

* ``gc.freeze()``: the objects the imports made (hundreds of thousands with torch) move to the
  permanent generation, so no collection in the server or in a worker forked from it walks
  them again (a walk also writes to their pages, which copy-on-write then copies into every
  worker).
* The server ends when the last process that uses it exits. It holds that process's stdout
  and stderr (a child keeps fds 0-2), so whoever reads them (a shell pipe, ``subprocess.run``,
  CI) waits for the server's interpreter teardown, which took 1.2-1.4 s after the driver had
  exited on the 2-core EPYC of benchmarks/README.md. The server has nothing to flush or
  close (its workers are separate processes, and they leave with ``os._exit`` already), so
  its exit skips that teardown: an exit handler ends it with ``os._exit(0)``.

Importing this module anywhere else would do the same to that process: only the fork server
should import it.
"""

from __future__ import annotations

import atexit
import gc
import os
import sys

__all__: list[str] = []


def _exit_now() -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


gc.collect()
gc.freeze()
atexit.register(_exit_now)
