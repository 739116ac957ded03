"""Console entry points that compose the packages: ``dit-slam`` (runtime, and sim for the default sequence) and
``dit-eval`` (runtime's trajectory evaluation, train's depth evaluation)."""

import os

# One OpenBLAS thread for numpy and scipy, set before they load (a user's own setting wins): the runtime's matrices
# are small, and OpenBLAS's idle threads spin on the second core that the dense system's network thread needs (a
# keyframe's prior measured 45 ms of CPU with the default threads, 16 ms with one).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
