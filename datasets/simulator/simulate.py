"""Simulate a recording on a floor plan: true house, route, LiDAR scans, wheel odometry, partial map.

Frames (REP-105): ``map`` = the true house's metric frame (plan units mapped by
``distortion.matrix``); ``odom`` starts at the first true pose; ``base_link`` is the robot; the
laser (frame ``laser``) sits at ``base_link``. Units: metres, radians, seconds; stamps are
absolute (``options.start_time`` + time since the route's start), integer nanoseconds in the bag.

:func:`simulate_run` returns everything in memory (:class:`SimulatedRun`); :func:`simulate`
also writes ``out_dir``:

- ``bag/``: ROS 2 bag (rosbags, sqlite3): ``/scan`` sensor_msgs/LaserScan (``inf`` = no return,
  ``nan`` = dropout), ``/odom`` nav_msgs/Odometry (``odom`` -> ``base_link``, at ``odom_rate``),
  ``/ground_truth`` nav_msgs/Odometry (``map`` -> ``base_link``, at each scan stamp),
  ``/tf_static`` (``base_link`` -> ``laser``, identity);
- ``ground_truth.tum``: ``stamp x y z qx qy qz qw`` at each scan stamp;
- ``house.json``: the true house and the distortion (:class:`House` JSON);
- ``map.yaml`` + ``map.pgm``: the partial LiDAR map (map_server) in the ``map`` frame;
- ``plan.json``: the plan as given (plan units); ``meta.json``: options, seed, lidar, counts.

The files are staged and moved into place together (:class:`~frslam_graph.atomic.OutputFolder`),
``meta.json`` last with the list of outputs: a folder without it is not a complete simulation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from frslam_graph.datasets.scan import Scan
from frslam_graph.datasets.simulator.distortion import Distortion
from frslam_graph.datasets.simulator.house import House
from frslam_graph.datasets.simulator.lidar import Lidar, RayCaster
from frslam_graph.datasets.simulator.odometry import OdometryNoise, OdometryTrack, wheel_odometry
from frslam_graph.datasets.simulator.partial_map import explored_fraction, partial_map
from frslam_graph.datasets.simulator.route import Route, RouteParams, plan_route
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from frslam_graph.atomic import OutputFolder, atomic_write
from frslam_graph.errors import ConfigError, RecordingError
from frslam_graph.floorplan import FloorPlan
from frslam_graph.occupancy import OccupancyGrid

FORMAT_NAME = "frslam-simulation"
FORMAT_VERSION = 1
OUTPUT_FILES = ("bag", "ground_truth.tum", "house.json", "meta.json", "map.yaml", "map.pgm", "plan.json")

Progress = Callable[[str, float], None]  # (stage, fraction done in [0, 1])


class SimulationOptions(BaseModel):
    """Everything :func:`simulate` can vary (metres, seconds, degrees where named ``_deg``)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    # route
    rooms: list[str] | None = None  # room sequence; None = every reachable room, then random
    start_room: str | None = None
    length: float = Field(0.0, ge=0.0, le=1e5)  # minimum route length, metres
    max_speed: float = Field(0.5, gt=0.0, le=2.0)
    max_turn_rate: float = Field(1.0, gt=0.0, le=3.0)  # rad/s
    # house
    closed_doors: int = Field(0, ge=0)  # number of interior doors closed at random
    closed_door_ids: list[str] = Field(default_factory=list)
    clutter: int = Field(0, ge=0, le=500)
    wall_thickness: float = Field(0.12, gt=0.0, le=1.0)
    # distortion
    rotation: Literal["step90", "any", "none"] = "step90"
    aspect_max: float = Field(0.3, ge=0.0, lt=1.0)
    flip_prob: float = Field(0.5, ge=0.0, le=1.0)
    metres_per_unit: float | None = Field(None, gt=0.0, le=1e4)
    house_diagonal: tuple[float, float] = (10.0, 25.0)  # metres, when metres_per_unit is None
    # lidar
    beams: int = Field(1081, ge=2, le=100_000)
    fov_deg: float = Field(270.0, gt=0.0, le=360.0)
    max_range: float = Field(30.0, gt=0.0, le=1000.0)
    min_range: float = Field(0.05, ge=0.0)
    range_noise: float = Field(0.01, ge=0.0, lt=1.0)
    dropout: float = Field(0.0, ge=0.0, lt=1.0)
    scan_rate: float = Field(10.0, gt=0.0, le=100.0)
    caster: Literal["auto", "sweep", "open3d", "naive"] = "auto"
    # odometry
    odom_rate: float = Field(50.0, ge=1.0, le=1000.0)
    odom_scale_error: float = Field(0.02, gt=-0.5, lt=0.5)
    odom_turn_scale_error: float = Field(0.01, gt=-0.5, lt=0.5)
    odom_dist_noise: float = Field(0.02, ge=0.0, lt=1.0)
    odom_heading_noise_deg: float = Field(1.0, ge=0.0, lt=45.0)
    odom_turn_noise_deg: float = Field(0.5, ge=0.0, lt=45.0)
    # partial map
    map_completeness: float = Field(0.5, gt=0.0, le=1.0)
    map_resolution: float = Field(0.05, ge=0.005, le=1.0)
    map_noise: bool = True
    map_see_through_doors: bool = False
    # clock
    start_time: float = Field(1_700_000_000.0, ge=1.0, le=4e9)

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise _config_error(exc) from None

    def __setattr__(self, name: str, value: Any) -> None:
        try:
            super().__setattr__(name, value)
        except ValidationError as exc:
            raise _config_error(exc) from None

    @model_validator(mode="after")
    def _check(self) -> SimulationOptions:
        if self.min_range >= self.max_range:
            raise ValueError("min_range must be smaller than max_range")
        lo, hi = self.house_diagonal
        if not (0.0 < lo <= hi <= 1e4):
            raise ValueError("house_diagonal must be (low, high) metres with 0 < low <= high")
        return self

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> SimulationOptions:
        if data is None:
            return cls()
        if not isinstance(data, dict):
            raise ConfigError(f"expected a mapping, got {type(data).__name__}", where="simulation")
        return cls(**data)

    def lidar(self) -> Lidar:
        return Lidar(
            beams=self.beams,
            fov=math.radians(self.fov_deg),
            max_range=self.max_range,
            range_noise=self.range_noise,
            dropout=self.dropout,
            min_range=self.min_range,
        )

    def odometry_noise(self) -> OdometryNoise:
        return OdometryNoise(
            scale_error=self.odom_scale_error,
            turn_scale_error=self.odom_turn_scale_error,
            dist_noise=self.odom_dist_noise,
            heading_noise=math.radians(self.odom_heading_noise_deg),
            turn_noise=math.radians(self.odom_turn_noise_deg),
            rate=self.odom_rate,
        )

    def route_params(self) -> RouteParams:
        return RouteParams(max_speed=self.max_speed, max_turn_rate=self.max_turn_rate)


def _config_error(exc: ValidationError) -> ConfigError:
    err = exc.errors()[0]
    where = ".".join(["simulation", *(str(p) for p in err.get("loc", ()))])
    msg = err.get("msg", "invalid value")
    if err.get("type") == "value_error":
        msg = msg.removeprefix("Value error, ")
    elif "input" in err and err.get("type") != "missing":
        msg = f"{msg} (got {err['input']!r})"
    return ConfigError(msg, where=where)


@dataclass
class SimulatedRun:
    """A simulated recording in memory. Stamps are absolute seconds."""

    plan: FloorPlan
    house: House
    route: Route
    lidar: Lidar
    options: SimulationOptions
    seed: int
    stamps: np.ndarray  # (N,) scan stamps
    stamps_ns: np.ndarray  # (N,) int64
    true_poses: np.ndarray  # (N, 3) base_link in map at each scan
    odom_poses: np.ndarray  # (N, 3) base_link in odom at each scan
    ranges: np.ndarray  # (N, B) measured: inf = no return, nan = dropout / below min_range
    exact_ranges: np.ndarray  # (N, B) noise-free ray casting (inf = nothing within max_range)
    odometry: OdometryTrack  # at odom_rate, absolute stamps
    odometry_ns: np.ndarray  # (M,) int64 stamps of ``odometry``
    grid: OccupancyGrid
    map_rooms: list[str]
    caster_method: str = ""
    _scans: list[Scan] | None = field(default=None, repr=False)

    @property
    def distortion(self) -> Distortion:
        return self.house.distortion

    @property
    def ground_truth(self) -> np.ndarray:
        """(N, 4) stamp, x, y, theta of base_link in map at each scan."""
        return np.column_stack((self.stamps, self.true_poses))

    @property
    def map_completeness(self) -> float:
        return explored_fraction(self.house, self.map_rooms)

    @property
    def scans(self) -> list[Scan]:
        """One :class:`Scan` per stamp (``nan`` for every beam without a valid return)."""
        if self._scans is None:
            angles = self.lidar.angles
            r = np.where(np.isfinite(self.ranges), self.ranges, np.nan)
            self._scans = [
                Scan(
                    float(t), r[i], angles, tuple(float(v) for v in self.odom_poses[i]), self.lidar.max_range
                )
                for i, t in enumerate(self.stamps)
            ]
        return self._scans

    def __len__(self) -> int:
        return len(self.stamps)


def _close_random_doors(house_plan: FloorPlan, n: int, rng: np.random.Generator) -> list[str]:
    interior = [d.id for d in house_plan.doors if len(set(d.rooms)) == 2]
    if n > len(interior):
        raise ConfigError(
            f"cannot close {n} doors: the plan has {len(interior)} interior doors",
            where="simulation.closed_doors",
        )
    return [interior[i] for i in sorted(rng.choice(len(interior), size=n, replace=False))] if n else []


def simulate_run(
    plan: FloorPlan,
    seed: int = 0,
    options: SimulationOptions | None = None,
    progress: Progress | None = None,
) -> SimulatedRun:
    """Simulate a recording on ``plan`` in memory (see the module docstring)."""
    options = options or SimulationOptions()
    if not isinstance(plan, FloorPlan):
        raise ConfigError(f"expected a FloorPlan, got {type(plan).__name__}", where="plan")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {seed!r}", where="seed")
    report = progress or (lambda stage, frac: None)
    rng = np.random.default_rng(int(seed))
    report("house", 0.0)
    # Scale: given, else the plan's own metres per unit (a metric plan keeps its size, up to the
    # aspect error), else random for a realistic house (10-25 m diagonal by default).
    mpu = options.metres_per_unit if options.metres_per_unit is not None else plan.metres_per_unit
    distortion = Distortion.random(
        rng,
        rotation=options.rotation,
        aspect_max=options.aspect_max,
        flip_prob=options.flip_prob,
        metres_per_unit=mpu,
        plan_bounds=plan.bounds,
        diagonal_range=options.house_diagonal,
    )
    # Door links are needed to choose interior doors: link in plan units first when missing.
    base = plan
    if any(len(set(d.rooms)) < 2 for d in plan.doors):
        scale = max(distortion.sx, distortion.sy)
        linked = plan.link_doors(tol=max(0.3, 2.0 * options.wall_thickness) / scale)
        base = replace(
            plan,
            doors=[
                d if len(set(d.rooms)) == 2 else ld for d, ld in zip(plan.doors, linked.doors, strict=True)
            ],
        )
    closed = list(options.closed_door_ids) + _close_random_doors(
        _without(base, options.closed_door_ids), options.closed_doors, rng
    )
    house = House.from_plan(
        base,
        distortion,
        wall_thickness=options.wall_thickness,
        closed_doors=closed,
        clutter=options.clutter,
        rng=rng,
    )
    report("route", 0.0)
    route = plan_route(
        house,
        rng,
        rooms=options.rooms,
        length=options.length,
        start_room=options.start_room,
        params=options.route_params(),
    )
    lidar = options.lidar()
    n = int(math.floor(route.duration * options.scan_rate + 1e-9)) + 1
    t0_ns = int(round(options.start_time * 1e9))
    rel_ns = np.round(np.arange(n) * (1e9 / options.scan_rate)).astype(np.int64)
    stamps_ns = t0_ns + rel_ns
    true_poses = route.sample(rel_ns / 1e9)
    # odometry at its own rate (plus the last route instant), sampled at the scan stamps
    m = int(math.floor(route.duration * options.odom_rate + 1e-9)) + 1
    orel_ns = np.round(np.arange(m) * (1e9 / options.odom_rate)).astype(np.int64)
    odom_true = route.sample(orel_ns / 1e9)
    odom = wheel_odometry(orel_ns / 1e9, odom_true, options.odometry_noise(), rng)
    odom_at_scans = odom.sample(rel_ns / 1e9)
    odometry = OdometryTrack((t0_ns + orel_ns) / 1e9, odom.poses)
    # ray casting in chunks (progress)
    caster = RayCaster(house.segments, method=options.caster)
    exact = np.empty((n, lidar.beams))
    angles = lidar.angles
    chunk = 256
    for i0 in range(0, n, chunk):
        exact[i0 : i0 + chunk] = caster.cast(true_poses[i0 : i0 + chunk], angles, lidar.max_range)
        report("lidar", min(1.0, (i0 + chunk) / n))
    meas = exact + rng.normal(0.0, lidar.range_noise, size=exact.shape) if lidar.range_noise else exact.copy()
    meas[meas > lidar.max_range] = np.inf
    meas[meas < lidar.min_range] = np.nan
    if lidar.dropout > 0.0:
        meas[rng.random(size=exact.shape) < lidar.dropout] = np.nan
    report("map", 0.0)
    start_room = route.rooms[0]
    grid, map_rooms = partial_map(
        house,
        options.map_completeness,
        rng,
        resolution=options.map_resolution,
        start_room=start_room,
        noise=options.map_noise,
        see_through_doors=options.map_see_through_doors,
    )
    report("map", 1.0)
    return SimulatedRun(
        plan=plan,
        house=house,
        route=route,
        lidar=lidar,
        options=options,
        seed=int(seed),
        stamps=stamps_ns / 1e9,
        stamps_ns=stamps_ns,
        true_poses=true_poses,
        odom_poses=odom_at_scans,
        ranges=meas,
        exact_ranges=exact,
        odometry=odometry,
        odometry_ns=t0_ns + orel_ns,
        grid=grid,
        map_rooms=map_rooms,
        caster_method=caster.method,
    )


def _without(plan: FloorPlan, door_ids: list[str]) -> FloorPlan:
    """The plan minus the given doors (so random closing picks among the others)."""
    known = {d.id for d in plan.doors}
    bad = sorted(set(door_ids) - known)
    if bad:
        raise ConfigError(
            f"unknown door ids {bad} (the plan has {sorted(known)})", where="simulation.closed_door_ids"
        )
    drop = set(door_ids)
    return replace(plan, doors=[d for d in plan.doors if d.id not in drop])


@dataclass
class SimulationResult:
    """What :func:`simulate` wrote (paths) and a summary."""

    out_dir: Path
    bag: Path
    ground_truth: Path
    house: Path
    meta: Path
    map_yaml: Path
    plan: Path
    scans: int
    odometry: int
    route_length: float
    duration: float
    map_completeness: float
    map_rooms: list[str]
    distortion: Distortion
    run: SimulatedRun | None = field(default=None, repr=False)


def _quat(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.sin(theta / 2.0), np.cos(theta / 2.0)


def write_tum(path: Path, stamps: np.ndarray, poses: np.ndarray) -> Path:
    """TUM trajectory: ``stamp x y z qx qy qz qw`` (z = 0, yaw-only quaternion)."""
    qz, qw = _quat(poses[:, 2])
    rows = np.column_stack(
        (
            stamps,
            poses[:, 0],
            poses[:, 1],
            np.zeros(len(poses)),
            np.zeros(len(poses)),
            np.zeros(len(poses)),
            qz,
            qw,
        )
    )
    with atomic_write(path) as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw  (base_link in map, simulator ground truth)\n")
        for r in rows:
            fh.write(f"{r[0]:.9f} {r[1]:.17g} {r[2]:.17g} 0 0 0 {r[6]:.17g} {r[7]:.17g}\n")
    return path


def check_output_dir(out: Path, overwrite: bool, overwrite_option: str = "overwrite=True") -> list[str]:
    """The simulator files already in ``out`` (to be replaced); ConfigError when ``out`` is a file,
    or holds a previous simulation and ``overwrite`` is false (naming ``overwrite_option``, how the
    caller's user asks to replace it: the CLI's ``--overwrite``)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError("output path exists and is not a folder", source=out)
    present = [name for name in OUTPUT_FILES if (out / name).exists()]
    if present and not overwrite:
        raise ConfigError(
            f"output folder already holds a simulation ({', '.join(present)}); to replace it: {overwrite_option}",
            source=out,
        )
    return present


def simulate(
    plan: FloorPlan | str | Path,
    out_dir: str | Path | OutputFolder,
    seed: int = 0,
    options: SimulationOptions | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    keep_run: bool = False,
) -> SimulationResult:
    """Simulate a recording on ``plan`` and write it to ``out_dir`` (see the module docstring).

    ``overwrite`` replaces the simulator's files in an existing folder; without it an existing
    bag or ground truth there is an error. ``out_dir`` may be an :class:`OutputFolder` declared
    (and checked) by the caller. ``keep_run`` attaches the in-memory run to the result.
    """
    if not isinstance(plan, FloorPlan):
        plan = FloorPlan.load(plan)
    folder = (
        out_dir if isinstance(out_dir, OutputFolder) else OutputFolder(out_dir, "meta.json", OUTPUT_FILES)
    )
    out = folder.folder
    check_output_dir(out, overwrite)
    options = options or SimulationOptions()
    run = simulate_run(plan, seed, options, progress)
    report = progress or (lambda stage, frac: None)
    with folder:
        folder.write("bag", lambda p: write_bag(run, p, progress=report))
        folder.write("ground_truth.tum", lambda p: write_tum(p, run.stamps, run.true_poses))
        folder.write("house.json", run.house.save)
        folder.write("map.yaml", run.grid.save)
        folder.write("plan.json", plan.save)
        folder.commit(_meta(run, plan, options))
    return SimulationResult(
        out_dir=out,
        bag=out / "bag",
        ground_truth=out / "ground_truth.tum",
        house=out / "house.json",
        meta=out / "meta.json",
        map_yaml=out / "map.yaml",
        plan=out / "plan.json",
        scans=len(run),
        odometry=len(run.odometry.stamps),
        route_length=run.route.length,
        duration=run.route.duration,
        map_completeness=run.map_completeness,
        map_rooms=list(run.map_rooms),
        distortion=run.distortion,
        run=run if keep_run else None,
    )


def _meta(run: SimulatedRun, plan: FloorPlan, options: SimulationOptions) -> dict[str, Any]:
    """The content of ``meta.json`` (the folder's manifest)."""
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "seed": run.seed,
        "options": options.model_dump(mode="json"),
        "lidar": run.lidar.to_dict(),
        "odometry": options.odometry_noise().to_dict(),
        "caster": run.caster_method,
        "plan": {"name": plan.name, "source": plan.source, "units": plan.units, "rooms": len(plan.rooms)},
        "distortion": run.distortion.to_dict(),
        "frames": {"map": "map", "odom": "odom", "base_link": "base_link", "laser": "laser"},
        "sensor_offset": [0.0, 0.0, 0.0],
        "topics": {
            "scan": "/scan",
            "odom": "/odom",
            "ground_truth": "/ground_truth",
            "tf_static": "/tf_static",
        },
        "counts": {"scans": len(run), "odometry": len(run.odometry.stamps)},
        "start_time": options.start_time,
        "duration": run.route.duration,
        "route": {"length": run.route.length, "rooms": run.route.rooms},
        "closed_doors": list(run.house.closed_doors),
        "map": {
            "rooms": run.map_rooms,
            "completeness": run.map_completeness,
            "resolution": run.grid.resolution,
        },
        "files": {
            "bag": "bag",
            "ground_truth": "ground_truth.tum",
            "house": "house.json",
            "map": "map.yaml",
            "plan": "plan.json",
        },
    }


def write_bag(run: SimulatedRun, path: Path, progress: Progress | None = None) -> Path:
    """Write the run as a ROS 2 bag (see the module docstring) with rosbags."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]
    LaserScan = T["sensor_msgs/msg/LaserScan"]
    Odometry = T["nav_msgs/msg/Odometry"]
    PoseWithCovariance = T["geometry_msgs/msg/PoseWithCovariance"]
    TwistWithCovariance = T["geometry_msgs/msg/TwistWithCovariance"]
    Pose = T["geometry_msgs/msg/Pose"]
    Point = T["geometry_msgs/msg/Point"]
    Quaternion = T["geometry_msgs/msg/Quaternion"]
    Twist = T["geometry_msgs/msg/Twist"]
    Vector3 = T["geometry_msgs/msg/Vector3"]
    TFMessage = T["tf2_msgs/msg/TFMessage"]
    TransformStamped = T["geometry_msgs/msg/TransformStamped"]
    Transform = T["geometry_msgs/msg/Transform"]
    report = progress or (lambda stage, frac: None)

    def stamp(ns: int):
        return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))

    zero_cov = np.zeros(36, dtype=np.float64)
    opts = run.options
    noise = opts.odometry_noise()
    # odometry covariance per message is not meaningful for a drifting estimate: give a nominal one
    odom_cov = np.diag(
        [noise.dist_noise**2, noise.dist_noise**2, 1e6, 1e6, 1e6, noise.heading_noise**2]
    ).ravel()

    def odometry_msg(ns: int, frame: str, pose: np.ndarray, vel: np.ndarray, cov: np.ndarray):
        qz, qw = math.sin(pose[2] / 2.0), math.cos(pose[2] / 2.0)
        return Odometry(
            header=Header(stamp=stamp(ns), frame_id=frame),
            child_frame_id="base_link",
            pose=PoseWithCovariance(
                pose=Pose(
                    position=Point(x=float(pose[0]), y=float(pose[1]), z=0.0),
                    orientation=Quaternion(x=0.0, y=0.0, z=qz, w=qw),
                ),
                covariance=cov,
            ),
            twist=TwistWithCovariance(
                twist=Twist(
                    linear=Vector3(x=float(vel[0]), y=float(vel[1]), z=0.0),
                    angular=Vector3(x=0.0, y=0.0, z=float(vel[2])),
                ),
                covariance=zero_cov,
            ),
        )

    lidar = run.lidar
    path = Path(path)
    if path.exists():
        raise RecordingError("bag folder exists already", source=path)
    # Velocities of the true trajectory at the scan stamps (body frame).
    gt_vel = OdometryTrack(run.stamps, run.true_poses).velocities()
    odo_vel = run.odometry.velocities()
    # Merge all messages by time so the bag is written in order.
    events = [(int(ns), 1, i) for i, ns in enumerate(run.odometry_ns)]
    events += [(int(ns), 0, i) for i, ns in enumerate(run.stamps_ns)]
    events.sort()
    total = len(events)
    with Writer(path, version=8) as writer:
        c_scan = writer.add_connection("/scan", LaserScan.__msgtype__, typestore=ts)
        c_odom = writer.add_connection("/odom", Odometry.__msgtype__, typestore=ts)
        c_gt = writer.add_connection("/ground_truth", Odometry.__msgtype__, typestore=ts)
        c_tf = writer.add_connection("/tf_static", TFMessage.__msgtype__, typestore=ts)
        first = int(min(run.stamps_ns[0], run.odometry_ns[0]))
        tf = TFMessage(
            transforms=[
                TransformStamped(
                    header=Header(stamp=stamp(first), frame_id="base_link"),
                    child_frame_id="laser",
                    transform=Transform(
                        translation=Vector3(x=0.0, y=0.0, z=0.0),
                        rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                )
            ]
        )
        writer.write(c_tf, first, ts.serialize_cdr(tf, TFMessage.__msgtype__))
        empty = np.zeros(0, dtype=np.float32)
        ranges32 = run.ranges.astype(np.float32)
        for k, (ns, kind, i) in enumerate(events):
            if kind == 0:
                scan = LaserScan(
                    header=Header(stamp=stamp(ns), frame_id="laser"),
                    angle_min=float(lidar.angle_min),
                    angle_max=float(lidar.angle_max),
                    angle_increment=float(lidar.angle_increment),
                    time_increment=0.0,
                    scan_time=float(1.0 / opts.scan_rate),
                    range_min=float(lidar.min_range),
                    range_max=float(lidar.max_range),
                    ranges=ranges32[i],
                    intensities=empty,
                )
                writer.write(c_scan, ns, ts.serialize_cdr(scan, LaserScan.__msgtype__))
                gt = odometry_msg(ns, "map", run.true_poses[i], gt_vel[i], zero_cov)
                writer.write(c_gt, ns, ts.serialize_cdr(gt, Odometry.__msgtype__))
            else:
                od = odometry_msg(ns, "odom", run.odometry.poses[i], odo_vel[i], odom_cov)
                writer.write(c_odom, ns, ts.serialize_cdr(od, Odometry.__msgtype__))
            if k % 2000 == 0:
                report("bag", k / total)
    report("bag", 1.0)
    return path
