"""2D LiDAR + odometry simulator on real floor plans (true house, distortion, route, ray casting).

Units: metres, radians, seconds. Frames (REP-105): ``map`` = the true house's metric frame,
``odom`` starts at the first true pose, ``base_link`` the robot, ``laser`` at ``base_link``.

    from frslam_graph.datasets.simulator import simulate, simulate_run, SimulationOptions
    run = simulate_run(plan, seed=0, options=SimulationOptions(length=200))   # in memory
    res = simulate(plan, "out/", seed=0)                                       # bag + files
"""

from frslam_graph.datasets.simulator.distortion import Distortion
from frslam_graph.datasets.simulator.house import House, polygon_segments
from frslam_graph.datasets.simulator.lidar import Lidar, RayCaster, cast_naive, cast_sweep
from frslam_graph.datasets.simulator.odometry import OdometryNoise, OdometryTrack, wheel_odometry
from frslam_graph.datasets.simulator.partial_map import explored_fraction, grow_rooms, partial_map
from frslam_graph.datasets.simulator.route import Route, RouteParams, plan_route
from frslam_graph.datasets.simulator.simulate import (
    SimulatedRun,
    SimulationOptions,
    SimulationResult,
    simulate,
    simulate_run,
    write_bag,
    write_tum,
)
from frslam_graph.datasets.simulator.synthetic import five_room_plan

__all__ = [
    "Distortion",
    "House",
    "Lidar",
    "OdometryNoise",
    "OdometryTrack",
    "RayCaster",
    "Route",
    "RouteParams",
    "SimulatedRun",
    "SimulationOptions",
    "SimulationResult",
    "cast_naive",
    "cast_sweep",
    "explored_fraction",
    "five_room_plan",
    "grow_rooms",
    "partial_map",
    "plan_route",
    "polygon_segments",
    "simulate",
    "simulate_run",
    "wheel_odometry",
    "write_bag",
    "write_tum",
]
