"""refine-colmap's defaults, in one place: the library's arguments, `ari-sfm refine-colmap` and `ari-sfm sfm`
read them here (a light module: the command line shows them without loading pycolmap)."""
from __future__ import annotations

HUBER_PX = 2.0  # the Huber threshold of the reprojection residuals (px)
MAX_ITERATIONS = 100  # the final refinement's cap on accepted LM steps. LM stops at convergence, usually far
#   earlier (16-18 on the 28/100-image grids, 8-77 on the 200-image strips after their sliding start): the cap
#   only bounds a crawl along a long chain's soft mode
