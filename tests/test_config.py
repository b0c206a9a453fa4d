"""The configuration: defaults unchanged, every field described, a readable dump, typo hints."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from frslam_graph.cli import main
from frslam_graph.config import BASIC_KEYS, FRSlamConfig, OdometryConfig
from frslam_graph.errors import ConfigError

DATA = Path(__file__).parent / "data"


def test_defaults_are_those_recorded_before_the_descriptions():
    """tests/data/config_defaults.json is FRSlamConfig().model_dump() of the code before the
    fields got their descriptions (commit eb968a9): describing a field must not change it. A
    default changed on purpose is changed here too, in the same commit (since then:
    odometry.local_map_scans added)."""
    recorded = json.loads((DATA / "config_defaults.json").read_text())
    assert FRSlamConfig().model_dump() == recorded


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
        graph={"batch_relative_tolerance": 1e-7, "factorization": "CHOLESKY"},
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
