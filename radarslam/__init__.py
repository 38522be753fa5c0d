"""radarslam: radar SLAM for nuScenes-style automotive radar (five Continental ARS408 units).

Heavy libraries (torch, open3d, gtsam, kiss_icp) are imported lazily inside the modules that need
them, so ``import radarslam`` and ``radarslam --help`` stay fast.
"""

import os as _os

# torch, open3d and kiss-icp each bring an OpenMP/TBB pool; with the default active wait, a pool
# keeps spinning after its parallel region and starves the next library's threads. On 2 cores
# that made the place-recognition CNN 3.5x slower inside the SLAM loop. Passive waiting costs
# nothing measurable; it must be set before any of those runtimes start, and a user's explicit
# setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
