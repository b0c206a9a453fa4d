"""``run`` / ``compare`` take the reader options of ``inspect`` (``--scan-topic``, ``--odom-topic``,
``--laser``, ``--odom``); a bad value is one line naming the option and the file's choices, exit 2."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from frslam_graph.cli import main
from frslam_graph.errors import OptionError
from frslam_graph.resources import bundled
from tests import synthetic_world as sw
from tests.test_rosbag import LASER, ODOM, Msgs, write_bag

PLAN = str(bundled("r2v/000209a30b61b563f93faf6a6466ffab_0001.txt"))


@pytest.fixture(scope="module")
def two_topic_bag(tmp_path_factory):
    """A ROS 1 bag with two LaserScan topics (``/front_scan`` sees the room, ``/rear_scan`` is
    empty) and two odometry topics whose names both say odom: nothing can be auto-detected."""
    m = Msgs(True)
    truth = sw.route([(1.5, 1.5), (6.0, 1.5)], speed=0.6, rate=5.0)[:30]
    world = sw.room_world()
    msgs = []
    for t, x, y, th in truth:
        stamp = 100.0 + t
        ranges, amin, inc = sw.cast(world, np.array([x, y, th]), n_beams=360, max_range=20.0)
        front = m.scan(stamp, np.nan_to_num(ranges, nan=np.inf), angle_min=amin, inc=inc, rmax=20.0)
        msgs.append(("/front_scan", LASER, stamp, front))
        msgs.append(("/rear_scan", LASER, stamp, m.scan(stamp, [np.inf] * 8)))
        msgs.append(("/odom_wheel", ODOM, stamp - 0.001, m.odom(stamp - 0.001, x, y, th)))
        msgs.append(("/odom_fused", ODOM, stamp - 0.001, m.odom(stamp - 0.001, x, y, th)))
    msgs.sort(key=lambda r: r[2])
    return write_bag(tmp_path_factory.mktemp("bag") / "two.bag", msgs), len(truth)


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def test_run_names_the_scan_topic_option_and_the_bags_scan_topics(two_topic_bag, tmp_path, capsys):
    bag, _ = two_topic_bag
    assert main(["run", str(bag), "--out", str(tmp_path / "o")]) == 2
    err = one_line_error(capsys)
    assert "--scan-topic" in err and "choose one" in err and "/front_scan, /rear_scan" in err
    assert "scan_topic=" not in err
    assert main(["run", str(bag), "--scan-topic", "/nope", "--out", str(tmp_path / "o")]) == 2
    err = one_line_error(capsys)
    assert "--scan-topic /nope: no such topic (choices: /front_scan, /rear_scan)" in err
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_run_names_the_odom_topic_option_and_the_bags_odometry_topics(two_topic_bag, tmp_path, capsys):
    bag, _ = two_topic_bag
    argv = ["run", str(bag), "--scan-topic", "/front_scan", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = one_line_error(capsys)
    assert "--odom-topic: several Odometry topics" in err and "/odom_fused, /odom_wheel, '' (none)" in err
    assert main([*argv, "--odom-topic", "/front_scan"]) == 2
    assert "--odom-topic /front_scan: has type sensor_msgs/msg/LaserScan" in one_line_error(capsys)


def test_run_reads_the_chosen_topics(two_topic_bag, tmp_path, capsys):
    bag, n = two_topic_bag
    out = tmp_path / "o"
    argv = ["run", str(bag), "--scan-topic", "/front_scan", "--odom-topic", "/odom_wheel", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["scans"] == n
    no_odom = tmp_path / "no_odom"
    argv = ["run", str(bag), "--scan-topic", "/front_scan", "--odom-topic", "", "--out", str(no_odom)]
    assert main(argv) == 0
    assert json.loads((no_odom / "metrics.json").read_text())["scans"] == n


def test_run_on_a_carmen_log_names_the_laser_and_odom_choices(small_log, test_data, tmp_path, capsys):
    log, _ = small_log
    out = ["--out", str(tmp_path / "o")]
    assert main(["run", str(log), "--laser", "rear", *out]) == 2
    err = one_line_error(capsys)
    assert (
        str(log) in err
        and "--laser rear: no RLASER/ROBOTLASER2 records in the log (choices: front, all)" in err
    )
    assert main(["run", str(log), "--laser", "left", *out]) == 2
    assert "--laser left: no such laser (choices: front, rear, all)" in one_line_error(capsys)
    assert main(["run", str(log), "--odom", "odom", *out]) == 2
    assert "--odom odom: no usable ODOM records in the log (choices: auto, laser, none)" in one_line_error(
        capsys
    )
    assert main(["run", str(log), "--odom", "wheels", *out]) == 2
    assert "--odom wheels: no such odometry source (choices: auto, laser, odom, none)" in one_line_error(
        capsys
    )
    assert main(["run", str(log), "--scan-topic", "/scan", *out]) == 2
    assert "--scan-topic does not apply to a CARMEN log (its options: --laser, --odom)" in one_line_error(
        capsys
    )


def test_run_takes_the_odometry_of_the_odom_records(test_data, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["run", str(test_data / "intel_head.clf.bz2"), "--odom", "odom", "--out", str(out)]) == 0
    assert json.loads((out / "metrics.json").read_text())["scans"] == 64


def test_compare_takes_the_reader_options(two_topic_bag, small_log, tmp_path, capsys):
    bag, _ = two_topic_bag
    out = ["--floor-plan", PLAN, "--out", str(tmp_path / "c")]
    assert main(["compare", str(bag), "--scan-topic", "/front_scan", *out]) == 2
    assert "--odom-topic: several Odometry topics" in one_line_error(capsys)
    assert main(["compare", str(small_log[0]), "--laser", "rear", *out]) == 2
    assert "--laser rear: no RLASER/ROBOTLASER2 records in the log (choices: front, all)" in one_line_error(
        capsys
    )
    assert not (tmp_path / "c" / "compare.json").exists()


def test_inspect_names_the_options_as_run_does(two_topic_bag, capsys):
    bag, _ = two_topic_bag
    assert main(["inspect", str(bag), "--laser", "rear"]) == 2
    assert "--laser does not apply to a ROS bag (its options: --scan-topic, --odom-topic, --plane-tol)" in (
        one_line_error(capsys)
    )


def test_an_option_error_keeps_its_fields_across_processes(small_log):
    from frslam_graph.datasets import open_recording

    with pytest.raises(OptionError) as got:
        open_recording(small_log[0], laser="rear")
    back = pickle.loads(pickle.dumps(got.value))
    assert (back.option, back.value, back.choices, str(back)) == (
        "laser",
        "rear",
        ("front", "all"),
        str(got.value),
    )
