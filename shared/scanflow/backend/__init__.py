"""SLAM back end: keyframes, loop closures and the pose graph behind the front end.

    mapper = Mapper(frontend, BackendSettings(loop_closure=True))   # or Pipeline(..., backend=)
    step = mapper.add(frontend_output, points, no_return, mount)    # after every scan
    mapper.finish(); mapper.trajectory(); frontend.map              # optimised
    graph = PoseGraph(); graph.add_node(pose); graph.add_edge(a, b, motion, information)
    report = graph.optimise(robust_scale=2.0)                       # OptimiseReport

`pose_graph` is the least-squares core, `loops` finds and measures closures, `mapper` ties them
to the front end.
"""

from scanflow.backend.loops import LoopClosure, LoopDetector, ScanNode, loop_candidates
from scanflow.backend.mapper import Mapper, MapperStep, SavedRun
from scanflow.backend.pose_graph import OptimiseReport, PoseGraph

__all__ = [
    "LoopClosure",
    "LoopDetector",
    "Mapper",
    "MapperStep",
    "OptimiseReport",
    "PoseGraph",
    "SavedRun",
    "ScanNode",
    "loop_candidates",
]
