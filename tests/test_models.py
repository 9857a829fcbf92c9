"""Model packages (romannet/models.py): pack a small trained checkpoint, read it back, start a learner from it.

A tiny model (8 channels, 1 residual block) trained for a few updates on synthetic transitions stands in for
a run; its evaluation report is built by the evaluator's own report code. The learner test runs the real
service loop on two loopback Zenoh sessions and fetches its first weights as an actor does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import _learner_helpers as H
import pytest
import safetensors.torch
import torch

from romannet.cli import build_parser, main
from romannet.common.config import Config, ModelConfig, load_config
from romannet.common.configbase import write_toml
from romannet.common.errors import RomannetError
from romannet.common.model import RoManNet, state_dict_to_tensors
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.zenoh_session import free_port, make_config, open_session
from romannet.learner.checkpoint import (
    FP32_IN_PACKAGE,
    read_init_weights,
    read_package,
    save_checkpoint,
    to_package_dtypes,
)
from romannet.learner.service import ServiceOptions, run_learner
from romannet.learner.trainer import Trainer
from romannet.models import MAX_PACKAGE_BYTES, pack, resolve_model_dir

ROOT = Path(__file__).resolve().parents[1]
SETS = ["model.channels=8", "model.residual_blocks=1", 'learner.precision="fp32"', "learner.num_threads=1",
        'run_id="models-test"']
PACKAGE_FILES = {"weights.safetensors", "config.toml", "report.json", "report.md", "model.json"}


def _config() -> Config:
    return load_config(None, SETS)


def _train_run(run_dir: Path, updates: int = 3) -> Trainer:
    """A run directory as the learner leaves it: config.toml, metrics.csv, a checkpoint after `updates`."""
    cfg = _config()
    run_dir.mkdir(parents=True)
    write_toml(cfg, run_dir / "config.toml")
    trainer = Trainer(cfg.model, cfg.learner, cfg.reward, cfg.task, exploration_cfg=cfg.exploration)
    rows = ["update,loss,replay_inserts"]
    for k in range(updates):
        trainer.train_step(H.batch(2, seed=20 + k))
        rows.append(f"{trainer.updates},0.5,{40 + 10 * trainer.updates}.0")
    (run_dir / "metrics.csv").write_text("\n".join(rows) + "\n")
    save_checkpoint(trainer, run_dir)
    return trainer


def _eval_dir(path: Path, updates: int, completed: int, runs: int = 3, protocol: str = "frozen") -> Path:
    """A `romannet eval` output directory: `completed` of `runs` clutter runs completed."""
    from romannet.evaluate.metrics import RunLog, StepLog
    from romannet.evaluate.report import build_report, markdown

    logs = [RunLog("clutter", 100 + i, 3, "done", (StepLog("pick", True),) * 3) if i < completed else
            RunLog("clutter", 100 + i, 3, "consecutive_failures", (StepLog("pick", False),) * 10)
            for i in range(runs)]
    header = {"checkpoint": "ckpt", "updates": updates, "task": "clutter", "protocol": protocol,
              "runs_per_case": runs, "base_seed": 100, "planned_runs": runs, "interrupted": False, "workers": 1,
              "machine": "test", "date": "2026-01-01T00:00:00", "wall_s": 1.0, "object_set": "blocks",
              "num_objects": 3, "goal_heights": None, "cases_dir": None, "overrides": [], "config": "config.toml"}
    report = build_report(logs, header)
    path.mkdir(parents=True, exist_ok=True)
    (path / "report.json").write_text(json.dumps(report))
    (path / "report.md").write_text(markdown(report))
    return path


@pytest.fixture(autouse=True)
def _cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """resolve_model_dir's copies go to the test's directory, not the user's cache."""
    monkeypatch.setenv("ROMANNET_CACHE_DIR", str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Trainer]:
    torch.set_num_threads(1)
    run_dir = tmp_path_factory.mktemp("runs") / "clutter-run"
    return run_dir, _train_run(run_dir)


def _cli(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str]:
    code = main(list(argv))
    return code, capsys.readouterr().err


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _rounded(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """What a package gives back for fp32 tensors: bf16 rounding, BN running statistics as they were."""
    return {k: v.to(torch.bfloat16).float() if v.is_floating_point() and not k.endswith(FP32_IN_PACKAGE) else v
            for k, v in tensors.items()}


def test_pack_writes_a_complete_small_package(run, tmp_path):
    run_dir, trainer = run
    out = pack(run_dir, _eval_dir(tmp_path / "eval", 3, 2), tmp_path / "models" / "clutter")
    assert {p.name for p in out.iterdir()} == PACKAGE_FILES
    meta = json.loads((out / "model.json").read_text())
    weights = (out / "weights.safetensors").read_bytes()
    assert meta["weights"]["sha256"] == hashlib.sha256(weights).hexdigest()
    assert (meta["updates"], meta["checkpoint"], meta["training_actions"]) == (3, "ckpt-000000003", 70)
    assert meta["source_run"] == str(run_dir) and meta["experiment"] == "clutter" and meta["date"]
    assert meta["main_metric"]["value"] == pytest.approx(2 / 3)
    assert (out / "config.toml").read_bytes() == (run_dir / "config.toml").read_bytes()
    assert (out / "report.md").read_text() == (tmp_path / "eval" / "report.md").read_text()
    stored = safetensors.torch.load(weights)
    assert stored.keys() == trainer.state_tensors().keys()
    for k, v in stored.items():
        expected = torch.float32 if k.endswith(FP32_IN_PACKAGE) else torch.bfloat16
        assert v.dtype == (expected if v.is_floating_point() else torch.int64), k
    assert sum(p.stat().st_size for p in out.iterdir()) <= MAX_PACKAGE_BYTES


def test_pack_writes_the_resolved_config_without_removed_options(run, tmp_path):
    """A run trained by an older version names options since removed (at the values that kept them off): the
    package's config is today's resolved config, so it loads without them and says the same thing."""
    run_dir, _ = run
    cfg_path = run_dir / "config.toml"
    text = cfg_path.read_text()
    cfg_path.write_text(text.replace("[model]\n", "[model]\ndropout = 0.0\n", 1))
    assert "dropout" in cfg_path.read_text()
    out = pack(run_dir, _eval_dir(tmp_path / "eval", 3, 2), tmp_path / "models" / "clutter")
    packed = (out / "config.toml").read_text()
    assert "dropout" not in packed
    assert load_config(out / "config.toml") == load_config(cfg_path)


def test_the_default_model_fits_in_a_package():
    """3 nets x 1.9 M parameters: 11.5 MB in bf16, under the 15 MB a package may take."""
    packed = to_package_dtypes(state_dict_to_tensors(RoManNet(ModelConfig())))
    size = len(safetensors.torch.save(packed))
    assert 11_000_000 < size < MAX_PACKAGE_BYTES - 1_000_000


def test_loading_gives_the_bf16_rounding_in_fp32_to_learner_actor_and_eval(run, tmp_path):
    run_dir, trainer = run
    out = pack(run_dir, _eval_dir(tmp_path / "eval", 3, 2), tmp_path / "clutter")
    expected = _rounded(trainer.state_tensors())
    assert any(not torch.equal(expected[k], v) for k, v in trainer.state_tensors().items())  # bf16 did round
    tensors, meta, cfg = read_package(out)
    assert cfg == _config()
    for k, v in tensors.items():
        assert v.dtype == trainer.state_tensors()[k].dtype and torch.equal(v, expected[k]), k
    init, what = read_init_weights(out, cfg.model)
    assert all(torch.equal(init[k], expected[k]) for k in expected) and "update 3" in what
    # The evaluator reads the checkpoint-like copy with its own loader.
    from romannet.evaluate.runner import load_model_tensors

    ckpt, config_path = resolve_model_dir(out)
    assert config_path == out / "config.toml"
    got = load_model_tensors(ckpt)
    assert all(torch.equal(got[k], expected[k]) for k in expected)
    assert resolve_model_dir(out)[0] == ckpt  # written once, reused
    assert ckpt.is_relative_to(tmp_path / "cache")


def test_eval_plans_a_package_with_the_proposed_resolve_checkpoint(run, tmp_path, monkeypatch):
    """The change evaluate/cli.py's resolve_checkpoint needs: a model.json directory resolves through
    resolve_model_dir, the package directory standing for the run (its config.toml, its name)."""
    import romannet.evaluate.cli as evcli

    original = evcli.resolve_checkpoint

    def resolve_checkpoint(path: Path) -> tuple[Path, Path]:
        if (path / "model.json").is_file():
            return resolve_model_dir(path)[0], path
        return original(path)

    monkeypatch.setattr(evcli, "resolve_checkpoint", resolve_checkpoint)
    out = pack(run[0], _eval_dir(tmp_path / "eval", 3, 2), tmp_path / "models" / "clutter")
    args = build_parser().parse_args(["eval", str(out), "--task", "clutter", "--objects", "3", "--runs", "2"])
    plan = evcli.plan_checkpoint(args, out)
    assert plan.config_path == out / "config.toml" and plan.state["updates"] == 3
    assert plan.name == "clutter" and len(plan.specs) == 2


def test_pack_replaces_only_a_worse_package_unless_forced(run, tmp_path, capsys):
    run_dir, _ = run
    out = tmp_path / "models" / "clutter"
    pack(run_dir, _eval_dir(tmp_path / "e2", 3, 2), out)
    sha = json.loads((out / "model.json").read_text())["weights"]["sha256"]
    for name, completed in (("e1", 1), ("e2b", 2)):  # worse, then as good: refused, package untouched
        code, err = _cli(capsys, "models", "pack", str(run_dir), "--eval", str(_eval_dir(tmp_path / name, 3,
                                                                                                 completed)),
                         "--out", str(out))
        assert code == 2 and "not better" in _one_line(err) and "66.7%" in err
        assert json.loads((out / "report.json").read_text())["overall"]["completed"] == 2
    code, err = _cli(capsys, "models", "pack", str(run_dir), "--eval",
                     str(_eval_dir(tmp_path / "paper", 3, 3, protocol="paper")), "--out", str(out))
    assert code == 2 and "not comparable" in _one_line(err)
    pack(run_dir, _eval_dir(tmp_path / "e3", 3, 3), out)  # better: replaced
    assert json.loads((out / "report.json").read_text())["overall"]["completed"] == 3
    assert main(["models", "pack", str(run_dir), "--eval", str(tmp_path / "e1"), "--out", str(out), "--force"]) == 0
    assert json.loads((out / "report.json").read_text())["overall"]["completed"] == 1
    assert json.loads((out / "model.json").read_text())["weights"]["sha256"] == sha
    assert not list(out.parent.glob(".*"))  # no staging or old directories left


def test_pack_refuses_reports_and_places_that_do_not_fit(run, tmp_path, capsys):
    run_dir, _ = run
    other = _eval_dir(tmp_path / "other", 7, 2)
    code, err = _cli(capsys, "models", "pack", str(run_dir), "--eval", str(other), "--out", str(tmp_path / "m"))
    assert code == 2 and "evaluated update 7" in _one_line(err)
    (tmp_path / "nomd").mkdir()
    (tmp_path / "nomd" / "report.json").write_text("{}")
    code, err = _cli(capsys, "models", "pack", str(run_dir), "--eval", str(tmp_path / "nomd"), "--out",
                     str(tmp_path / "m"))
    assert code == 2 and "report.md missing" in _one_line(err)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    code, err = _cli(capsys, "models", "pack", str(run_dir), "--eval", str(_eval_dir(tmp_path / "ok", 3, 2)),
                     "--out", str(busy))
    assert code == 2 and "not a model package" in _one_line(err) and (busy / "notes.txt").exists()
    code, err = _cli(capsys, "models", "pack", str(tmp_path / "ok"), "--eval", str(tmp_path / "ok"), "--out",
                     str(tmp_path / "m"))
    assert code == 2 and "neither a model package" in _one_line(err)
    assert not (tmp_path / "m").exists()


def _broken_packages(good: Path, tmp: Path) -> dict[str, tuple[Path, str]]:
    """name: (package directory, what its one error line says)."""
    import shutil

    def copy(name: str) -> Path:
        return Path(shutil.copytree(good, tmp / name))

    def rewrite_weights(pkg: Path, data: bytes) -> None:
        (pkg / "weights.safetensors").write_bytes(data)
        meta = json.loads((pkg / "model.json").read_text())
        meta["weights"]["sha256"] = hashlib.sha256(data).hexdigest()
        (pkg / "model.json").write_text(json.dumps(meta))

    cases = {}
    missing = copy("missing")
    (missing / "weights.safetensors").unlink()
    cases["missing"] = (missing, "weights.safetensors missing")
    corrupt = copy("corrupt")
    rewrite_weights(corrupt, b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all")
    cases["corrupt"] = (corrupt, "not a readable safetensors file")
    flipped = copy("flipped")
    data = bytearray((flipped / "weights.safetensors").read_bytes())
    data[-3] ^= 0xFF
    (flipped / "weights.safetensors").write_bytes(bytes(data))
    cases["flipped"] = (flipped, "the file is corrupt or was replaced")
    shapes = copy("shapes")
    wider = to_package_dtypes(state_dict_to_tensors(RoManNet(ModelConfig(channels=4, residual_blocks=1))))
    rewrite_weights(shapes, safetensors.torch.save(wider))
    cases["shapes"] = (shapes, "has shape")
    nan = copy("nan")
    tensors = safetensors.torch.load((nan / "weights.safetensors").read_bytes())
    tensors["nets.pick.conv1.weight"][0, 0, 0, 0] = float("nan")
    rewrite_weights(nan, safetensors.torch.save(tensors))
    cases["nan"] = (nan, "NaN")
    return cases


def test_bad_packages_are_one_clear_line(run, tmp_path, capsys):
    good = pack(run[0], _eval_dir(tmp_path / "eval", 3, 2), tmp_path / "good")
    assert main(["models", "check", str(good)]) == 0 and "sha256 ok" in capsys.readouterr().out
    for name, (pkg, says) in _broken_packages(good, tmp_path).items():
        code, err = _cli(capsys, "models", "check", str(pkg))
        assert code == 2 and says in _one_line(err), (name, err)
        with pytest.raises(RomannetError, match=says):
            resolve_model_dir(pkg)
    code, err = _cli(capsys, "models", "check", str(good), "--init", *[a for s in SETS for a in ("--set", s)],
                     "--set", "model.channels=16")
    assert code == 2 and "trained with model channels=8, this run has channels=16" in _one_line(err)
    code, err = _cli(capsys, "models", "check", str(run[0] / "checkpoints"), "--init")
    assert code == 2 and "is neither a model package (model.json), a checkpoint" in _one_line(err)


def test_init_from_accepts_runs_and_checkpoints_exactly(run):
    run_dir, trainer = run
    cfg = _config()
    ckpt = run_dir / "checkpoints" / "ckpt-000000003"
    for source in (run_dir, ckpt):
        tensors, what = read_init_weights(source, cfg.model)
        assert "update 3" in what
        assert all(torch.equal(tensors[k], v) for k, v in trainer.state_tensors().items())
    # Inference settings may differ from the source's; the architecture may not.
    read_init_weights(run_dir, dataclasses.replace(cfg.model, precision="fp32", num_threads=2))
    with pytest.raises(RomannetError, match="rotation_harmonics=2, this run has rotation_harmonics=1"):
        read_init_weights(run_dir, dataclasses.replace(cfg.model, rotation_harmonics=1))


class _EmptyReplay:
    """A replay server that never holds enough transitions: the learner publishes and waits."""

    def stats(self, timeout_s: float = 10.0) -> dict[str, Any]:
        return {"size": 0, "inserts": 0}

    def sample(self, batch_size: int, timeout_s: float = 10.0) -> Any:
        raise AssertionError("the learner sampled from an empty replay")

    def update_priorities(self, update: Any) -> None:
        raise AssertionError("no sample, no priorities")

    def insert(self, transition: Any, timeout_s: float = 10.0) -> Any:
        raise AssertionError("the learner does not insert")

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> Any:
        raise AssertionError("the learner does not insert")


def test_learner_init_from_a_package_publishes_its_weights_as_version_0(run, tmp_path):
    out = pack(run[0], _eval_dir(tmp_path / "eval", 3, 2), tmp_path / "models" / "clutter")
    cfg = load_config(None, [*SETS, "learner.target_network=true"])
    init, _ = read_init_weights(out, cfg.model)
    expected = _rounded(run[1].state_tensors())
    stop, trainers, result = threading.Event(), [], {}
    port = free_port()
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as learner_session, \
            open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as actor_session:

        def learn() -> None:
            result["summary"] = run_learner(cfg, tmp_path / "ft", _EmptyReplay(), learner_session, stop,
                                            options=ServiceOptions(idle_wait_s=0.05, plot_every_s=3600),
                                            ready=trainers.append, init_weights=init)

        thread = threading.Thread(target=learn)
        with ZenohWeightsSource(actor_session, cfg.run_id, fetch_timeout_s=5) as source:
            thread.start()
            try:
                deadline, got = time.monotonic() + 60, None
                while got is None and time.monotonic() < deadline and thread.is_alive():
                    got = source.poll_weights()
                    time.sleep(0.05)
            finally:
                stop.set()
                thread.join(60)
    assert got is not None, "no weights reached the actor"
    version, weights = got
    assert version == 0 and weights.keys() == expected.keys()
    assert all(torch.equal(weights[k], expected[k]) for k in expected)
    trainer = trainers[0]
    assert trainer.updates == 0 and not trainer.optimizer.state
    assert all(torch.equal(v, expected[k]) for k, v in state_dict_to_tensors(trainer.target).items())
    assert result["summary"]["updates"] == 0
    state = json.loads((tmp_path / "ft" / "checkpoints" / "ckpt-000000000" / "state.json").read_text())
    assert state["updates"] == 0


def test_learner_cli_checks_init_from_before_connecting(run, tmp_path, capsys):
    config = tmp_path / "run.toml"
    write_toml(load_config(None, [*SETS, "model.channels=4"]), config)
    base = ["learner", "--config", str(config), "--connect", "tcp/127.0.0.1:1"]
    code, err = _cli(capsys, *base, "--run-dir", str(tmp_path / "a"), "--init-from", str(run[0]))
    assert code == 2 and "channels=8, this run has channels=4" in _one_line(err)
    code, err = _cli(capsys, *base, "--run-dir", str(tmp_path / "b"), "--init-from", str(tmp_path / "none"))
    assert code == 2 and "is not a directory" in _one_line(err)
    code, err = _cli(capsys, *base, "--run-dir", str(run[0]), "--resume", "--init-from", str(run[0]))
    assert code == 2 and "pass one of them" in _one_line(err)


def test_up_checks_init_from_first_and_passes_it_to_a_learner_without_checkpoint(run, tmp_path):
    from romannet.fleet import ActorLedger
    from romannet.up import build_specs, check_init_from

    sets = [a for s in SETS for a in ("--set", s)]
    args = build_parser().parse_args(["up", "--actors", "1", "--max-actions", "0", "--init-from", str(run[0]),
                                      *sets, "--set", "model.channels=4"])
    with pytest.raises(RomannetError, match="channels=8, this run has channels=4") as err:
        check_init_from(args)  # a `romannet models check --init` process, as `up` runs it
    assert "\n" not in str(err.value)
    resumed = build_parser().parse_args(["up", "--resume", "--init-from", str(run[0])])
    with pytest.raises(RomannetError, match="pass one of them"):
        check_init_from(resumed)
    run_dir = tmp_path / "fleet"
    specs = {s.name: s for s in build_specs(run_dir, _config(), args, "tcp/a:1", "tcp/b:2",
                                            ActorLedger.load(tmp_path / "ledger.json"))}
    argv = specs["learner"].argv()
    assert argv[argv.index("--init-from") + 1] == str(run[0].resolve()) and "--resume" not in argv
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "LATEST").write_text("ckpt-000000100")
    argv = specs["learner"].argv()  # a restart after its first checkpoint resumes it instead
    assert "--resume" in argv and "--init-from" not in argv


# ----------------------------------------------------------------------------------------------------------
# Shipped models (models/<experiment>/): each must beat uniformly random valid actions on its own tests.

SHIPPED = sorted(p for p in (ROOT / "models").glob("*") if (p / "model.json").is_file())
MARGIN = 0.2  # pooled pick success over random's; completion must not be lower either


def _eval_cmd(pkg: Path, out: Path, *extra: str) -> list[str]:
    report = json.loads((pkg / "report.json").read_text())
    argv = [sys.executable, "-m", "romannet.cli", "eval", str(pkg), "--protocol", "frozen", "--runs", "3",
            "--task", report["task"], "--out", str(out), *extra]
    if report["task"] == "clutter":  # the training scene's 10 objects: a 30-object run takes minutes on 2 cores
        argv += ["--objects", str(min(10, report["num_objects"])), "--object-set", report["object_set"]]
    if report["task"] == "stacking":
        argv += ["--goal-height", *[str(h) for h in report["goal_heights"]]]
    return argv


def _eval_has_random_policy() -> bool:
    try:
        build_parser().parse_args(["eval", "x", "--policy", "random"])
    except SystemExit:
        return False
    return True


@pytest.mark.parametrize("pkg", SHIPPED or [pytest.param(None, marks=pytest.mark.skip(
    reason="models/ holds no package yet (romannet models pack ... --out models/<experiment>)"))],
    ids=[p.name for p in SHIPPED] or ["no-models"])
@pytest.mark.timeout(3600)
def test_shipped_model_beats_the_random_policy(pkg, tmp_path):
    if not _eval_has_random_policy():
        pytest.skip("romannet eval has no --policy random to compare with")
    overall = {}
    for name, extra in (("net", ()), ("random", ("--policy", "random"))):
        done = subprocess.run(_eval_cmd(pkg, tmp_path / name, *extra), capture_output=True, text=True,
                              env={**os.environ, "ROMANNET_CACHE_DIR": str(tmp_path / "cache")}, timeout=3000)
        assert done.returncode == 0, done.stderr[-2000:]
        overall[name] = json.loads((tmp_path / name / "report.json").read_text())["overall"]
    net, rnd = overall["net"], overall["random"]
    assert net["completion_rate"] >= rnd["completion_rate"], overall
    assert (net["pick_success_all_runs"] or 0.0) >= (rnd["pick_success_all_runs"] or 0.0) + MARGIN, overall
