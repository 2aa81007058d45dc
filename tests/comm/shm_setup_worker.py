"""Run under torchrun at two ranks: rank 0 sets up a SharedMemoryAllReduce while rank 1 takes part in the set-up's
first collective (the names' broadcast) and then holds back, so that rank 0 stays between the creation of the segment
and pipes and their unlink (in the set-up's first barrier) for as long as the test needs to SIGKILL it there."""

from __future__ import annotations

import time

from ftrain.comm import group
from ftrain.comm.shm_allreduce import SharedMemoryAllReduce

if __name__ == "__main__":
    info = group.init(120)
    if info.rank == 0:
        SharedMemoryAllReduce(info, capacity=100, timeout_s=120)
    else:
        group.broadcast_object(None, info, None, src=0)  # the names, as the reducer's set-up receives them
        time.sleep(120)
