"""Stand-in worker targets for ``dego.evaluation.run._run_workers`` (importable by the
spawned processes): one that is killed as the OOM killer kills, one that runs until it
is stopped."""

from __future__ import annotations

import os
import signal
import time
from typing import Any


def killed_worker(rank: int, *args: Any) -> None:
    """Rank 1 dies by SIGKILL at once; rank 0 waits to be stopped."""
    if rank == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(60)


def busy_worker(rank: int, plan: Any, world_size: int, store: str, *args: Any) -> None:
    """Ignores SIGINT as the real worker does, writes a file beside the store (to show it
    ran), then runs until it is stopped."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with open(f"{store}.{rank}", "w") as mark:
        mark.write(str(os.getpid()))
    time.sleep(60)
