"""Test session setup.

BLAS runs single-threaded in tests (and in the node processes they start, which inherit the
environment): the suite runs ROS nodes, replays and estimators side by side on a 2-core CI
machine, and oversubscribed OpenBLAS threads made some estimators 10x slower there.
"""
import os
import sys
from pathlib import Path

for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

sys.path.insert(0, str(Path(__file__).resolve().parent))   # test helpers: bagfactory, modal_data, ...

from rosgraph import domain_id  # noqa: E402

# tests run in parallel workers (pytest-xdist): a graph started without its own domain must not
# meet another worker's graph, and DDS stays on loopback
os.environ["ROS_DOMAIN_ID"] = str(domain_id(211))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
