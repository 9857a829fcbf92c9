"""The `romannet` command as a user runs it: real processes, real exit codes, real output."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def romannet(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROMANNET_LOG_LEVEL="WARNING")
    return subprocess.run([sys.executable, "-m", "romannet.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s, env=env, cwd=ROOT)


def test_help_lists_verbs_with_examples():
    out = romannet("--help")
    assert out.returncode == 0
    assert "info" in out.stdout and "bench" in out.stdout
    assert "romannet info --json" in out.stdout
    sub = romannet("bench", "--help")
    assert sub.returncode == 0 and "example:" in sub.stdout and "romannet bench inference --json" in sub.stdout


def test_help_and_usage_errors_do_not_import_torch():
    # torch takes ~2-3 s to import on a 2-core box: every verb's --help and every bad flag answer at once.
    code = ("import sys\nfrom romannet.cli import main\nfor argv in (['--help'], ['eval', '--help'], "
            "['sweep', '--help'], ['up', '--bogus']):\n    try:\n        main(argv)\n    except SystemExit:\n"
            "        pass\nprint('torch' in sys.modules, file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.stderr.strip().splitlines()[-1] == "False", out.stderr[-2000:]


def test_info_json_reports_parameters_and_resolved_config():
    out = romannet("info", "--json", "--set", "reward.push_weight=0.4")
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert set(info["parameters_per_net"]) == {"push", "pick", "place"}
    for count in info["parameters_per_net"].values():
        assert 1_700_000 < count < 2_100_000  # "about 1.9 M parameters per net"
    assert info["config"]["reward"]["push_weight"] == 0.4
    assert info["heightmap_px"] == [224, 224]
    assert info["torch_threads"] >= 1


def test_info_human_readable_prints_the_resolved_config():
    out = romannet("info")
    assert out.returncode == 0, out.stderr
    assert "parameters per net" in out.stdout and "[reward]" in out.stdout


def test_bad_override_is_one_clear_line_and_exit_2():
    out = romannet("info", "--set", "exploration.beta=2")
    assert out.returncode == 2
    assert "exploration.beta" in out.stderr and "[0, 1)" in out.stderr
    assert "Traceback" not in out.stderr


def test_missing_config_file_is_a_clear_error(tmp_path):
    out = romannet("info", "--config", str(tmp_path / "missing.toml"))
    assert out.returncode == 2 and "does not exist" in out.stderr


def test_local_zenoh_config_opens_a_real_session():
    zenoh = pytest.importorskip("zenoh")
    cfg = zenoh.Config.from_json5((ROOT / "deploy" / "zenoh-local.json5").read_text())
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    with zenoh.open(cfg) as session:
        assert str(session.zid())


def test_sim_snapshot_writes_a_png_with_the_action_drawn(tmp_path):
    import cv2

    out = tmp_path / "snap.png"
    run = romannet("sim", "snapshot", "--task", "stacking", "--seed", "1", "--out", str(out),
                   "--action", "pick:112:90:30", "--set", "sim.robot=gripper")
    assert run.returncode == 0, run.stderr
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] >= 224 and image.shape[1] > 3 * 224  # camera + 2 heightmaps
    bad = romannet("sim", "snapshot", "--out", str(out), "--action", "pick:1:2")
    assert bad.returncode == 2 and "primitive:row:col:angle_deg" in bad.stderr
