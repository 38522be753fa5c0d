"""radarslam: radar SLAM for nuScenes-style automotive radar (five Continental ARS408 units).

Heavy libraries (torch, open3d, gtsam, kiss_icp) are imported lazily inside the modules that need
them, so ``import radarslam`` and ``radarslam --help`` stay fast.
"""

__version__ = "0.1.0"
