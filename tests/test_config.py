"""The configuration: defaults unchanged, every field described, a readable dump, typo hints."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest
import yaml

from frslam_graph.cli import main
from frslam_graph.config import BASIC_KEYS, FRSlamConfig, OdometryConfig
from frslam_graph.errors import ConfigError

DATA = Path(__file__).parent / "data"

#: config fields removed in issue 20 (their defaults were never changed by a test, tool or doc): each is now
#: a constant of its one reader, ``module: name``, with the recorded default
REMOVED = {
    "graph.anchor_sigma_theta_deg": ("frslam_graph.backend.graph", "ANCHOR_SIGMA_THETA_DEG"),
    "graph.anchor_sigma_xy": ("frslam_graph.backend.graph", "ANCHOR_SIGMA_XY"),
    "graph.batch_max_iterations": ("frslam_graph.backend.graph", "BATCH_MAX_ITERATIONS"),
    "graph.between_sigma_floor_theta_deg": ("frslam_graph.backend.graph", "BETWEEN_SIGMA_FLOOR_THETA_DEG"),
    "graph.between_sigma_floor_xy": ("frslam_graph.backend.graph", "BETWEEN_SIGMA_FLOOR_XY"),
    "graph.prior_settle_near_theta_deg": ("frslam_graph.backend.graph", "PRIOR_SETTLE_NEAR_THETA_DEG"),
    "graph.prior_settle_near_xy": ("frslam_graph.backend.graph", "PRIOR_SETTLE_NEAR_XY"),
    "loop_closure.batch_on_correction": ("frslam_graph.loop_closure.closer", "BATCH_ON_CORRECTION"),
    "loop_closure.candidate_spacing": ("frslam_graph.loop_closure.closer", "CANDIDATE_SPACING"),
    "loop_closure.coarse_step_theta_deg": (
        "frslam_graph.loop_closure.submap_matching",
        "COARSE_STEP_THETA_DEG",
    ),
    "loop_closure.coarse_step_xy": ("frslam_graph.loop_closure.submap_matching", "COARSE_STEP_XY"),
    "loop_closure.confirm_theta_deg": ("frslam_graph.loop_closure.closer", "CONFIRM_THETA_DEG"),
    "loop_closure.confirm_xy": ("frslam_graph.loop_closure.closer", "CONFIRM_XY"),
    "loop_closure.consistency_theta_deg": ("frslam_graph.loop_closure.closer", "CONSISTENCY_THETA_DEG"),
    "loop_closure.consistency_xy": ("frslam_graph.loop_closure.closer", "CONSISTENCY_XY"),
    "loop_closure.covariance_inflation": ("frslam_graph.loop_closure.closer", "CLOSURE_COVARIANCE_INFLATION"),
    "loop_closure.icp_iterations": ("frslam_graph.loop_closure.submap_matching", "ICP_ITERATIONS"),
    "loop_closure.icp_max_distance": ("frslam_graph.loop_closure.submap_matching", "ICP_MAX_DISTANCE"),
    "loop_closure.icp_sigma": ("frslam_graph.loop_closure.submap_matching", "ICP_SIGMA"),
    "loop_closure.inlier_distance": ("frslam_graph.loop_closure.submap_matching", "INLIER_DISTANCE"),
    "loop_closure.max_lookups_per_step": (
        "frslam_graph.loop_closure.submap_matching",
        "MAX_LOOKUPS_PER_STEP",
    ),
    "loop_closure.max_query_points": ("frslam_graph.loop_closure.submap_matching", "MAX_QUERY_POINTS"),
    "loop_closure.min_coarse_score": ("frslam_graph.loop_closure.submap_matching", "MIN_COARSE_SCORE"),
    "loop_closure.min_keyframe_gap": ("frslam_graph.loop_closure.closer", "MIN_KEYFRAME_GAP"),
    "loop_closure.min_rotation_gap_deg": ("frslam_graph.loop_closure.closer", "MIN_ROTATION_GAP_DEG"),
    "loop_closure.min_travel_gap": ("frslam_graph.loop_closure.closer", "MIN_TRAVEL_GAP"),
    "loop_closure.peak_separation_theta_deg": (
        "frslam_graph.loop_closure.submap_matching",
        "PEAK_SEPARATION_THETA_DEG",
    ),
    "loop_closure.peak_separation_xy": ("frslam_graph.loop_closure.submap_matching", "PEAK_SEPARATION_XY"),
    "loop_closure.prune_theta_deg": ("frslam_graph.loop_closure.closer", "PRUNE_THETA_DEG"),
    "loop_closure.prune_xy": ("frslam_graph.loop_closure.closer", "PRUNE_XY"),
    "loop_closure.query_travel": ("frslam_graph.loop_closure.closer", "QUERY_TRAVEL"),
    "loop_closure.radius_base": ("frslam_graph.loop_closure.closer", "RADIUS_BASE"),
    "loop_closure.radius_max": ("frslam_graph.loop_closure.closer", "RADIUS_MAX"),
    "loop_closure.radius_per_m": ("frslam_graph.loop_closure.closer", "RADIUS_PER_M"),
    "loop_closure.refine_ratio": ("frslam_graph.loop_closure.submap_matching", "REFINE_RATIO"),
    "loop_closure.sigma_floor_theta_deg": (
        "frslam_graph.loop_closure.closer",
        "CLOSURE_SIGMA_FLOOR_THETA_DEG",
    ),
    "loop_closure.sigma_floor_xy": ("frslam_graph.loop_closure.closer", "CLOSURE_SIGMA_FLOOR_XY"),
    "loop_closure.submap_keyframes": ("frslam_graph.loop_closure.closer", "SUBMAP_KEYFRAMES"),
    "loop_closure.submap_travel": ("frslam_graph.loop_closure.closer", "SUBMAP_TRAVEL"),
    "loop_closure.theta_window_base_deg": ("frslam_graph.loop_closure.closer", "THETA_WINDOW_BASE_DEG"),
    "loop_closure.theta_window_per_m_deg": ("frslam_graph.loop_closure.closer", "THETA_WINDOW_PER_M_DEG"),
    "loop_closure.theta_window_per_turn": ("frslam_graph.loop_closure.closer", "THETA_WINDOW_PER_TURN"),
    "odometry.degenerate_sigma": ("frslam_graph.odometry.scan_odometry", "DEGENERATE_SIGMA"),
    "odometry.gap_factor": ("frslam_graph.odometry.scan_odometry", "GAP_FACTOR"),
    "odometry.icp_cov_inflation": ("frslam_graph.odometry.scan_odometry", "ICP_COV_INFLATION"),
    "odometry.icp_sigma_floor_theta_deg": (
        "frslam_graph.odometry.scan_odometry",
        "ICP_SIGMA_FLOOR_THETA_DEG",
    ),
    "odometry.icp_sigma_floor_xy": ("frslam_graph.odometry.scan_odometry", "ICP_SIGMA_FLOOR_XY"),
    "odometry.min_motion": ("frslam_graph.odometry.scan_odometry", "MIN_MOTION"),
    "odometry.odom_jump_gate": ("frslam_graph.odometry.scan_odometry", "ODOM_JUMP_GATE"),
    "odometry.odom_jump_min_deg": ("frslam_graph.odometry.scan_odometry", "ODOM_JUMP_MIN_DEG"),
    "odometry.odom_jump_min_m": ("frslam_graph.odometry.scan_odometry", "ODOM_JUMP_MIN_M"),
    "updates.backfill_per_keyframe": ("frslam_graph.plan_updates.priors", "BACKFILL_PER_KEYFRAME"),
    "updates.check_growth_per_m": ("frslam_graph.plan_updates.judge", "CHECK_GROWTH_PER_M"),
    "updates.gate_drift_deg_per_m": ("frslam_graph.plan_updates.priors", "GATE_DRIFT_DEG_PER_M"),
    "updates.gate_drift_frac": ("frslam_graph.plan_updates.priors", "GATE_DRIFT_FRAC"),
    "updates.gate_sigma_theta_deg": ("frslam_graph.plan_updates.priors", "GATE_SIGMA_THETA_DEG"),
    "updates.gate_sigma_xy": ("frslam_graph.plan_updates.priors", "GATE_SIGMA_XY"),
    "updates.inconsistent_chi2": ("frslam_graph.plan_updates.priors", "INCONSISTENT_CHI2"),
    "updates.local_map_distance": ("frslam_graph.plan_updates.schedule", "LOCAL_MAP_DISTANCE"),
    "updates.obstruction_speed": ("frslam_graph.plan_updates.updater", "OBSTRUCTION_SPEED"),
    "updates.obstruction_time_s": ("frslam_graph.plan_updates.updater", "OBSTRUCTION_TIME_S"),
    "updates.prior_kind": ("frslam_graph.plan_updates.priors", "PRIOR_KIND"),
    "updates.refine_scan_margin": ("frslam_graph.plan_updates.judge", "REFINE_SCAN_MARGIN"),
    "updates.register_growth_frac": ("frslam_graph.plan_updates.schedule", "REGISTER_GROWTH_FRAC"),
    "updates.reloc_cov_inflation": (
        "frslam_graph.localisation.relocalisation",
        "RelocaliserParams.cov_inflation",
    ),
    "updates.reloc_inlier_distance": (
        "frslam_graph.localisation.relocalisation",
        "RelocaliserParams.inlier_distance",
    ),
    "updates.reloc_max_ambiguity": ("frslam_graph.plan_updates.priors", "RELOC_MAX_AMBIGUITY"),
    "updates.reloc_window_max_theta_deg": ("frslam_graph.plan_updates.priors", "RELOC_WINDOW_MAX_THETA_DEG"),
    "updates.reloc_window_max_xy": ("frslam_graph.plan_updates.priors", "RELOC_WINDOW_MAX_XY"),
    "updates.remove_chi2": ("frslam_graph.plan_updates.priors", "REMOVE_CHI2"),
    "updates.remove_max_share": ("frslam_graph.plan_updates.priors", "REMOVE_MAX_SHARE"),
    "updates.remove_min_theta_deg": ("frslam_graph.plan_updates.priors", "REMOVE_MIN_THETA_DEG"),
    "updates.remove_min_xy": ("frslam_graph.plan_updates.priors", "REMOVE_MIN_XY"),
    "updates.scale_reanchor_xy": ("frslam_graph.plan_updates.refiner", "SCALE_REANCHOR_XY"),
    "updates.scale_refine_margin": ("frslam_graph.plan_updates.refiner", "SCALE_REFINE_MARGIN"),
    "updates.scale_refine_max": ("frslam_graph.plan_updates.refiner", "SCALE_REFINE_MAX"),
    "updates.scale_refine_min": ("frslam_graph.plan_updates.refiner", "SCALE_REFINE_MIN"),
    "updates.scale_refine_sigma": ("frslam_graph.plan_updates.refiner", "SCALE_REFINE_SIGMA"),
    "updates.switch_margin": ("frslam_graph.plan_updates.judge", "SWITCH_MARGIN"),
}


def test_defaults_are_those_recorded_before_the_descriptions():
    """tests/data/config_defaults.json is FRSlamConfig().model_dump() of the code before the
    fields got their descriptions (commit eb968a9): describing a field must not change it. A
    default changed on purpose is changed here too, in the same commit (since then:
    odometry.local_map_scans and updates.background_registration_s added; the REMOVED fields
    left out; loop_closure.final_alignment_rounds 2 -> 1 in session 14)."""
    recorded = json.loads((DATA / "config_defaults.json").read_text())
    for key in REMOVED:
        section, name = key.split(".")
        del recorded[section][name]
    assert FRSlamConfig().model_dump() == recorded


@pytest.mark.parametrize("key", sorted(REMOVED))
def test_a_removed_field_is_a_constant_with_its_recorded_default(key):
    """Same value, same type: replacing the field by the constant changes no result."""
    section, name = key.split(".")
    recorded = json.loads((DATA / "config_defaults.json").read_text())[section][name]
    module, attr = REMOVED[key]
    value = importlib.import_module(module)
    for part in attr.split("."):
        value = getattr(value, part)
    assert value == recorded and type(value) is type(recorded)
    with pytest.raises(ConfigError, match="unknown key"):
        FRSlamConfig.from_dict({section: {name: recorded}})


def test_every_field_has_a_description():
    missing = [name for name, _field in _all_fields() if not _field.description]
    assert not missing, f"fields without a description: {missing}"


def _all_fields():
    for section, field in FRSlamConfig.model_fields.items():
        yield section, field
        for name, inner in field.annotation.model_fields.items():
            yield f"{section}.{name}", inner


@pytest.mark.parametrize(
    ("data", "where", "hint"),
    [
        ({"odometry": {"voxel_sise": 0.1}}, "odometry.voxel_sise", "did you mean odometry.voxel_size?"),
        ({"loop_closure": {"enable": False}}, "loop_closure.enable", "did you mean loop_closure.enabled?"),
        ({"odmetry": {"voxel_size": 0.1}}, "odmetry", "unknown section; did you mean odometry?"),
        ({"odometry": {"prior_kernel": "huber"}}, "odometry.prior_kernel", "did you mean graph.prior_kernel"),
    ],
)
def test_a_mistyped_key_names_it_and_the_closest_valid_keys(data, where, hint):
    with pytest.raises(ConfigError) as err:
        FRSlamConfig.from_dict(data, source="cfg.yaml")
    assert err.value.where == where
    assert hint in err.value.message and "frslam config dump --all" in err.value.message
    assert "Extra inputs" not in str(err.value)


def test_an_unknown_key_without_a_close_match_points_to_the_list():
    with pytest.raises(ConfigError, match=r"odometry\.qqqq: unknown key \(frslam config dump --all"):
        FRSlamConfig.from_dict({"odometry": {"qqqq": 1}})
    with pytest.raises(ConfigError, match="unknown section .expected one of odometry, graph"):
        FRSlamConfig.from_dict({"zzz": {}})
    with pytest.raises(ConfigError, match=r"odometry\.voxel_sise: unknown key; did you mean"):
        OdometryConfig(voxel_sise=0.1)


def test_run_with_a_mistyped_config_key_exits_2_with_one_line(small_log, tmp_path, capsys, monkeypatch):
    import frslam_graph.offline as offline

    monkeypatch.setattr(offline, "run_recording", lambda *a, **k: pytest.fail("the run started"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("odometry:\n  voxel_sise: 0.2\n")
    assert main(["run", str(small_log[0]), "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"{bad}: odometry.voxel_sise: unknown key; did you mean odometry.voxel_size?" in err


@pytest.mark.parametrize("every", [True, False])
def test_the_dump_loads_back_to_the_defaults(tmp_path, every):
    text = FRSlamConfig().to_yaml(None if every else BASIC_KEYS)
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    assert FRSlamConfig.load(path) == FRSlamConfig()
    loaded = yaml.safe_load(text)
    keys = {f"{s}.{k}" for s, fields in loaded.items() for k in fields}
    assert keys == ({name for name, _ in _all_fields() if "." in name} if every else set(BASIC_KEYS))


def test_the_dump_of_a_changed_config_loads_back_to_it(tmp_path):
    cfg = FRSlamConfig().with_updates(
        odometry={"voxel_size": 0.2, "fixed_threshold": 0.5},
        graph={"batch_relative_tolerance": 1e-7, "factorization": "QR"},
        loop_closure={"wall_budget_ms": 20.0, "enabled": False},
    )
    path = tmp_path / "cfg.yml"
    path.write_text(cfg.to_yaml())
    assert FRSlamConfig.load(path) == cfg


def test_the_dump_puts_each_description_above_its_key():
    lines = FRSlamConfig().to_yaml(BASIC_KEYS).splitlines()
    at = lines.index("  keyframe_distance: 0.3")
    assert lines[at - 1].startswith("  # m; keyframe every this much travel")
    assert lines[lines.index("odometry:") - 1].startswith("# KISS-ICP scan odometry")
    assert all(len(line) <= 100 for line in lines)


def test_basic_keys_are_about_a_dozen_real_fields():
    fields = {name for name, _ in _all_fields()}
    assert set(BASIC_KEYS) <= fields and 10 <= len(BASIC_KEYS) <= 16


def test_config_dump_prints_the_basic_tier_or_writes_every_key(tmp_path, capsys):
    assert main(["config", "dump"]) == 0
    assert capsys.readouterr().out == FRSlamConfig().to_yaml(BASIC_KEYS)
    out = tmp_path / "all.yaml"
    assert main(["config", "dump", "--all", "--out", str(out)]) == 0
    assert out.read_text() == FRSlamConfig().to_yaml()
    assert f"wrote {out}" in capsys.readouterr().out
    assert FRSlamConfig.load(out) == FRSlamConfig()


def test_config_dump_to_a_bad_out_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["config", "dump", "--out", str(tmp_path / "cfg.txt")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cfg.txt" in err and ".yaml" in err
    assert not (tmp_path / "cfg.txt").exists()


def test_a_string_for_a_number_is_refused():
    """pydantic parsed '10' as 10 (and 'true' was already refused as 1)."""
    from frslam_graph.errors import ConfigError

    with pytest.raises(ConfigError, match=r"odometry\.max_range: expected a number, got '10'"):
        FRSlamConfig.from_dict({"odometry": {"max_range": "10"}})


@pytest.mark.parametrize(
    "key", ["updates.map_resolution", "updates.reloc_resolution", "loop_closure.resolution"]
)
def test_grid_resolutions_below_a_centimetre_are_refused(key):
    """loop_closure.resolution: 1e-9 was accepted (a submap grid of 10^20 cells when a closure came)."""
    from frslam_graph.errors import ConfigError

    section, field = key.split(".")
    with pytest.raises(
        ConfigError, match=rf"{section}\.{field}: Input should be greater than or equal to 0\.01"
    ):
        FRSlamConfig.from_dict({section: {field: 1e-9}})
