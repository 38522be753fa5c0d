"""The back-end sections of a SLAM preset (``radarslam/configs/slam/<preset>.yaml``): pose graph,
loop verification and static map. The SLAM pipeline's config embeds :class:`BackendConfig`."""

from __future__ import annotations

from radarslam.config import StrictModel
from radarslam.slam.loop_closure import LoopVerifierConfig
from radarslam.slam.map import StaticMapConfig
from radarslam.slam.pose_graph import PoseGraphConfig


class BackendConfig(StrictModel):
    pose_graph: PoseGraphConfig = PoseGraphConfig()
    loop_verification: LoopVerifierConfig = LoopVerifierConfig()
    static_map: StaticMapConfig = StaticMapConfig()
