"""Errors a CLI user sees name the command's options, not Python calls; one line, exit 2; no
line of OpenCV's before ours; input quoted from a bad file is capped (issue 22, deliverable 5)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from frslam_graph.datasets.simulator import five_room_plan

from frslam_graph.cli import MAX_MESSAGE_CHARS, _one_line, main
from frslam_graph.resources import bundled
from tests.test_outputs_atomic import SIM_ARGS
from tests.test_rosbag import standard_messages, write_bag

R2V = str(bundled("r2v/000209a30b61b563f93faf6a6466ffab_0001.txt"))


def one_line(text: str) -> str:
    lines = [x for x in text.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


@pytest.fixture(scope="module")
def flat_json(tmp_path_factory):
    """The five-room plan in metres (as a registered plan is)."""
    plan = five_room_plan().transformed(np.diag([0.05, 0.05, 1.0]), units="m")
    return plan.save(tmp_path_factory.mktemp("nav") / "flat.json")


def test_navigate_names_from_when_the_start_is_the_bad_option(flat_json, tmp_path, capsys):
    out = str(tmp_path / "p.png")
    assert main(["navigate", str(flat_json), "--from", "-50", "-50", "--to", "bathroom", "--out", out]) == 2
    err = one_line(capsys.readouterr().err)
    assert "--from -50 -50: no path: start" in err and "--to" not in err
    assert main(["navigate", str(flat_json), "--from", "nan", "0", "--to", "bathroom", "--out", out]) == 2
    assert "--from nan 0: start must be a finite" in one_line(capsys.readouterr().err)
    assert main(["navigate", str(flat_json), "--from", "2", "2", "--to", "garage", "--out", out]) == 2
    err = one_line(capsys.readouterr().err)
    assert "--to garage: unknown room 'garage'" in err and "goal:" not in err


def test_navigate_names_resolution_and_clearance_with_their_values(flat_json, tmp_path, capsys):
    argv = [
        "navigate",
        str(flat_json),
        "--from",
        "2",
        "2",
        "--to",
        "bathroom",
        "--out",
        str(tmp_path / "p.png"),
    ]
    assert main([*argv, "--resolution", "0.00001"]) == 2
    err = one_line(capsys.readouterr().err)
    assert "--resolution 1e-05: plan too large to rasterise" in err and "bounds" not in err
    assert main([*argv, "--clearance", "-1"]) == 2
    assert "--clearance -1: clearance must be >= 0" in one_line(capsys.readouterr().err)


def test_navigate_on_an_unregistered_plan_names_the_command_not_a_python_call(tmp_path, capsys):
    assert main(["navigate", R2V, "--from", "0", "0", "--to", "r1", "--out", str(tmp_path / "p.png")]) == 2
    err = one_line(capsys.readouterr().err)
    assert "frslam register PLAN MAP.yaml" in err and "registration.apply" not in err


def test_register_with_an_unknown_seed_room_exits_2_before_registering(tmp_path, capsys):
    out = tmp_path / "reg"
    gmap = str(bundled("prbonn/GMap.yaml"))
    assert main(["register", R2V, gmap, "--seed-room", "nope", "--out", str(out)]) == 2
    err = one_line(capsys.readouterr().err)
    assert "--seed-room 'nope': no such room in the plan (its rooms: r0, r1," in err
    assert not (out / "report.json").exists()


def test_simulate_into_a_previous_simulation_names_overwrite(tmp_path, capsys):
    out = tmp_path / "sim"
    out.mkdir()
    (out / "ground_truth.tum").write_text("0 0 0 0 0 0 0 1\n")
    plan = five_room_plan().save(tmp_path / "five.json")
    assert main(["simulate", str(plan), "--out", str(out), *SIM_ARGS]) == 2
    err = one_line(capsys.readouterr().err)
    assert "to replace it: --overwrite" in err and "use overwrite" not in err


def test_a_damaged_image_gives_our_line_only_not_opencvs(tmp_path, capfd):
    cut = tmp_path / "cut.png"
    cut.write_bytes(bundled("prbonn/GMap.png").read_bytes()[:3000])
    (tmp_path / "cut.yaml").write_text("image: cut.png\nresolution: 0.05\norigin: [0, 0, 0]\n")
    assert main(["map", "show", str(tmp_path / "cut.yaml"), "--out", str(tmp_path / "m.png")]) == 2
    err = one_line(capfd.readouterr().err)
    assert err.startswith("error:") and "damaged" in err


def test_opencv_4_without_utils_logging_is_silenced_through_set_log_level(monkeypatch, tmp_path, capsys):
    """pyproject admits OpenCV >= 4.10, whose cv2.utils has no ``logging``: the CLI must not crash."""
    import types

    levels = []
    monkeypatch.setattr(cv2, "utils", types.SimpleNamespace(), raising=False)
    monkeypatch.setattr(cv2, "setLogLevel", levels.append, raising=False)
    assert main(["plan", "show", str(tmp_path / "missing.json"), "--out", str(tmp_path / "p.png")]) == 2
    assert levels == [0]
    assert "missing.json" in capsys.readouterr().err


def test_a_binary_file_named_clf_gives_a_short_line(tmp_path, capsys):
    junk = tmp_path / "junk.clf"
    junk.write_bytes(np.random.default_rng(7).integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    assert main(["run", str(junk), "--out", str(tmp_path / "o")]) == 2
    err = one_line(capsys.readouterr().err)
    assert len(err) < 300 and "lines of no known CARMEN record type" in err
    assert all(c.isprintable() for c in err)


def test_a_bag_cut_in_half_is_reported_as_truncated(tmp_path, capsys):
    bag = write_bag(tmp_path / "full.bag", standard_messages(ros1=True, n=50))
    data = bag.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    assert main(["inspect", str(cut)]) == 2
    err = one_line(capsys.readouterr().err)
    assert "truncated: the file (" in err and "ends in the middle of the record" in err
    assert "no LaserScan" not in err


@pytest.mark.parametrize("storage", ["SQLITE3", "MCAP"])
def test_a_ros2_bag_cut_in_half_may_be_damaged_or_cut_short(storage, tmp_path, capsys):
    from rosbags.rosbag2 import StoragePlugin

    bag = write_bag(
        tmp_path / "b", standard_messages(ros1=False, n=50), ros1=False, storage=StoragePlugin[storage]
    )
    data_file = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    assert main(["inspect", str(bag)]) == 2
    assert "rosbags cannot read it, the bag may be damaged or cut short (" in one_line(
        capsys.readouterr().err
    )


def test_error_lines_lose_control_characters_and_are_capped():
    assert _one_line("a\nb\x1b[31mc\x00") == "a b [31mc "
    long = _one_line("x" * 50_000)
    assert len(long) == MAX_MESSAGE_CHARS and long.endswith("...")


def test_a_map_image_without_a_yaml_names_resolution_and_map_show_takes_it(tmp_path, capsys):
    image = tmp_path / "gm.png"
    image.write_bytes(bundled("prbonn/GMap.png").read_bytes())
    assert main(["map", "show", str(image), "--out", str(tmp_path / "m.png")]) == 2
    err = one_line(capsys.readouterr().err)
    assert "give it with --resolution" in err and "OccupancyGrid" not in err
    assert main(["map", "show", str(image), "--resolution", "0.05", "--out", str(tmp_path / "m.png")]) == 0


# ---------------------------------------------------------------- options named as typed (tools/bad_inputs.py)
@pytest.fixture(scope="module")
def plan_json(tmp_path_factory):
    return five_room_plan().save(tmp_path_factory.mktemp("plan") / "plan.json")


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--beams", "-5"], "--beams -5: Input should be greater than or equal to 2"),
        (["--noise", "inf"], "--noise inf: "),
        (["--odom-heading-drift", "-3"], "--odom-heading-drift -3: "),
        (
            ["--metres-per-unit", "1e300"],
            "--metres-per-unit 1e+300: Input should be less than or equal to 10000",
        ),
    ],
)
def test_simulate_names_the_option_not_the_options_field(plan_json, tmp_path, capsys, args, said):
    """The message said 'simulation.beams' / 'simulation.range_noise', fields a CLI user never saw."""
    assert main(["simulate", str(plan_json), "--out", str(tmp_path / "s"), *args]) == 2
    err = one_line(capsys.readouterr().err)
    assert said in err and "simulation." not in err


def test_map_plan_register_and_demo_name_their_options(plan_json, tmp_path, capsys):
    img = tmp_path / "m.png"
    cv2.imwrite(str(img), np.full((40, 60), 255, np.uint8))
    out = str(tmp_path / "o.png")
    assert main(["map", "show", str(img), "--resolution", "nan", "--out", out]) == 2
    assert "--resolution nan: must be a positive number" in one_line(capsys.readouterr().err)
    yaml_map = bundled("prbonn/GMap.yaml")
    assert main(["map", "show", str(yaml_map), "--resolution", "0.1", "--out", out]) == 2
    assert one_line(capsys.readouterr().err).startswith("error: --resolution 0.1: a map_server YAML states")
    plan_img = tmp_path / "plan.png"
    drawn = np.full((100, 150), 255, np.uint8)
    drawn[10:14, 10:140] = drawn[86:90, 10:140] = drawn[10:90, 10:14] = drawn[10:90, 136:140] = 0
    cv2.imwrite(str(plan_img), drawn)
    assert main(["plan", "convert", str(plan_img), str(tmp_path / "p.json"), "--door-width", "1e9"]) == 2
    assert "--door-width 1e+09: door width 1e+09 px is wider than the 150x100 px image" in one_line(
        capsys.readouterr().err
    )  # was a numpy ArrayMemoryError traceback (888 PiB)
    assert (
        main(["register", str(plan_json), str(yaml_map), "--method", "magic", "--out", str(tmp_path / "r")])
        == 2
    )
    assert "--method magic: unknown registration method" in one_line(capsys.readouterr().err)
    assert main(["demo", "--length", "-5", "--out", str(tmp_path / "demo")]) == 2
    assert "--length -5: expected a finite length" in one_line(capsys.readouterr().err)
    assert not (tmp_path / "demo").exists()


def test_usage_errors_are_one_line_naming_the_help(plan_json, tmp_path, capsys):
    """typer drew a five-line box for an unknown option or a missing one."""
    assert main(["simulte"]) == 2
    assert (
        one_line(capsys.readouterr().err)
        == "error: No such command 'simulte'. Did you mean 'simulate'? (see: frslam --help)"
    )
    assert main(["simulate", str(plan_json), "--out", str(tmp_path / "s"), "--beams", "many"]) == 2
    err = one_line(capsys.readouterr().err)
    assert "Invalid value for '--beams'" in err and err.endswith("(see: frslam simulate --help)")
    assert main(["compare", "x.clf"]) == 2
    assert "Missing option '--floor-plan'" in one_line(capsys.readouterr().err)
    assert main(["--help"]) == 0


def test_relations_options_checked_and_a_relations_file_matching_nothing(tmp_path, capsys):
    traj = tmp_path / "t.tum"
    traj.write_text("".join(f"{100 + 0.2 * i:.6f} {0.05 * i:.4f} 0 0 0 0 0 1\n" for i in range(40)))
    rel = tmp_path / "r.relations"
    rel.write_text("".join(f"{5000 + i:.6f} {5001 + i:.6f} 0.25 0 0 0 0 0.025\n" for i in range(30)))
    assert main(["relations", str(traj), str(rel), "--tolerance", "nan"]) == 2
    assert "--tolerance nan: expected a finite number of seconds" in one_line(capsys.readouterr().err)
    assert main(["relations", str(traj), str(rel), "--interpolate", "-1"]) == 2
    assert "--interpolate -1: " in one_line(capsys.readouterr().err)
    assert main(["relations", str(traj), str(rel)]) == 2  # printed 'nan ± nan' and exit 0
    assert "r.relations: none of its 30 relations matches a pose" in one_line(capsys.readouterr().err)


def test_a_recording_without_a_usable_scan_is_an_error_without_outputs(tmp_path, capsys):
    """It ran, wrote empty outputs and a matplotlib warning, and exited 0."""
    log = tmp_path / "nanpose.clf"
    beams = " ".join(["2.0"] * 90)
    log.write_text(
        "".join(
            f"FLASER 90 {beams} nan nan nan nan nan nan {100 + i}.0 host {100 + i}.0\n" for i in range(10)
        )
    )
    out = tmp_path / "o"
    assert main(["run", str(log), "--out", str(out), "--sequential"]) == 2
    err = one_line(capsys.readouterr().err)
    assert "nanpose.clf: no usable scan (10 skipped: laser record with a non-finite pose" in err
    assert not out.exists() or not any(out.iterdir())


def test_plane_tol_must_be_a_positive_finite_thickness(tmp_path, capsys):
    folder = tmp_path / "clouds"
    folder.mkdir()
    (folder / "0001.pcd").write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1 2 0\n3 4 0\n"
    )
    assert main(["inspect", str(folder), "--plane-tol", "nan"]) == 2
    assert "--plane-tol nan: expected a positive finite thickness" in one_line(capsys.readouterr().err)
