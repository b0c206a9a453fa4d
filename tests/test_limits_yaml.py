"""YAML inputs (map_server YAML, room segmentation, config): no alias expansion, no duplicate keys,
values quoted in errors cut short, config numbers that are not booleans."""

from __future__ import annotations

import resource

import pytest

from frslam_graph.cli import main
from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, MapError
from frslam_graph.occupancy import OccupancyGrid

GIB = 1 << 30


def _rss_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def laughs(levels: int = 9) -> str:
    """A "billion laughs": each level a list of ten aliases of the level before (10**levels items)."""
    lines = ['a0: &a0 ["lol"]']
    for i in range(1, levels + 1):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    return "\n".join(lines)


def map_yaml(tmp_path, origin: str, extra: str = "", name: str = "map.yaml"):
    (tmp_path / "map.pgm").write_bytes(b"P5\n2 2\n255\n" + bytes(4))
    path = tmp_path / name
    path.write_text(f"{extra}\nimage: map.pgm\nresolution: 0.05\norigin: {origin}\n")
    return path


def test_an_alias_bomb_in_a_map_origin_is_refused(tmp_path):
    path = map_yaml(tmp_path, "*a9", extra=laughs())
    before = _rss_kib()
    with pytest.raises(MapError, match=r"map\.yaml: line \d+: malformed YAML \(aliases") as err:
        OccupancyGrid.load(path)
    assert len(str(err.value)) < 300
    assert (_rss_kib() - before) * 1024 < GIB // 4


def test_a_duplicate_key_in_a_map_yaml_is_refused(tmp_path):
    path = map_yaml(tmp_path, "[0, 0, 0]", extra="resolution: 0.1")
    with pytest.raises(MapError, match=r"map\.yaml: line 3: malformed YAML \(duplicate key 'resolution'\)"):
        OccupancyGrid.load(path)


def test_a_huge_origin_value_is_quoted_short(tmp_path):
    path = map_yaml(tmp_path, "[" + ", ".join(["1"] * 200_000) + "]")
    with pytest.raises(MapError, match=r"map\.yaml: origin: ") as err:
        OccupancyGrid.load(path)
    assert len(str(err.value)) < 300


def test_map_show_of_an_alias_bomb_exits_2_with_one_line(tmp_path, capsys):
    path = map_yaml(tmp_path, "*a9", extra=laughs(), name="bomb.yaml")
    assert main(["map", "show", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "bomb.yaml" in err and "aliases" in err
    assert len(err.splitlines()) == 1 and len(err) < 300


def test_an_alias_bomb_in_a_config_is_refused(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text(laughs() + "\nodometry:\n  max_iterations: *a9\n")
    before = _rss_kib()
    with pytest.raises(ConfigError, match=r"config\.yaml: line \d+: not valid yaml: aliases") as err:
        FRSlamConfig.load(path)
    assert len(str(err.value)) < 300
    assert (_rss_kib() - before) * 1024 < GIB // 4


def test_a_duplicate_key_in_a_config_is_refused(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("odometry:\n  max_iterations: 10\n  max_iterations: 20\n")
    with pytest.raises(ConfigError, match=r"config\.yaml: line 3: .*duplicate key 'max_iterations'"):
        FRSlamConfig.load(path)


def test_a_huge_config_value_is_quoted_short(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("odometry:\n  max_iterations: " + "9x" * 1_000_000 + "\n")
    with pytest.raises(ConfigError, match=r"config\.yaml: odometry\.max_iterations: ") as err:
        FRSlamConfig.load(path)
    assert len(str(err.value)) < 300


@pytest.mark.parametrize("key", ["odometry.max_iterations", "odometry.voxel_size"])
def test_a_boolean_is_not_a_config_number(tmp_path, key):
    section, name = key.split(".")
    path = tmp_path / "config.yaml"
    path.write_text(f"{section}:\n  {name}: true\n")
    with pytest.raises(ConfigError, match=rf"config\.yaml: {key}: expected a number, got True"):
        FRSlamConfig.load(path)


def test_a_boolean_field_still_takes_a_boolean(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("odometry:\n  scan_matching: false\n  max_iterations: 7\n")
    config = FRSlamConfig.load(path)
    assert config.odometry.scan_matching is False and config.odometry.max_iterations == 7
