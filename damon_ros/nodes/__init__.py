"""The ROS 2 nodes: thin adapters over the rclpy-free algorithms.

Linear-algebra libraries start one worker thread per core that busy-wait for work. In a
node that runs at SCHED_FIFO next to 1 kHz control loops those spinning threads stall
everything (measured: a 3 ms plan took 700 ms inside the planner node), so every node
process uses single-threaded BLAS/OpenMP unless the user asked otherwise. This must happen
before numpy is first imported, which is why it lives here.
"""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
