"""ari-sfm: calibrate cameras behind a flat refractive window (the ARI equation)."""
from __future__ import annotations

import os

# GTSAM's linear algebra runs single-threaded faster on the small blocks of
# bundle adjustment; set before numpy/gtsam load BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
