"""`romannet <verb>`: the single command-line entry point of the fleet.

Each verb's module is imported only when that verb runs, so `romannet --help` stays fast. The benchmarks'
sub-commands are romannet/cli_bench.py's, the run diagnostics' romannet/analyse/cli.py's, the "did you mean"
error handling romannet/cli_parser.py's.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable

from romannet import __version__
from romannet.cli_bench import add_bench_arguments, cmd_bench
from romannet.cli_parser import Parser, parse_args
from romannet.common.errors import RomannetError
from romannet.deploy.cli import (
    DEPLOY_EXAMPLE,
    ROUTER_EXAMPLE,
    add_deploy_arguments,
    add_router_arguments,
    add_zenoh_config_arg,
)
from romannet.logsetup import setup_logging

log = logging.getLogger("romannet.cli")

EXAMPLES = {
    "up": ("romannet up --config configs/experiments/clutter.toml --actors 2 --max-actions 2000\n"
           "  romannet up --config configs/experiments/clutter.toml --name demo --robot gripper --resolution 0.007 "
           "--max-actions 120   # a quick look: ~30 learner updates\n"
           "  romannet up --name demo --resume\n  romannet up --name demo --foxglove 8765"),
    "info": "romannet info --json --set model.channels=32",
    "bench": ("romannet bench inference --json\n  romannet bench replay --json --inserts 2000 --repeats 200\n"
              "  romannet bench sim --json --actions 10 --robots arm,gripper\n"
              "  romannet bench learner --json --batch-sizes 1,4,8 --repeats 10\n"
              "  romannet bench system --json --actions 30\n"
              "  romannet bench pick-geometry --hands panda,rg2 --cube-sizes 0.05,0.04\n"
              "  romannet bench place-geometry --hands panda,rg2 --cube-sizes 0.04\n"
              "  sudo romannet bench faults --json   # network namespaces: root"),
    "sim": "romannet sim snapshot --task stacking --seed 3 --out snapshot.png --action pick:112:90:30",
    "replay": "romannet replay --config configs/default.toml --dir runs/default/replay --listen tcp/127.0.0.1:7447\n"
              "  romannet replay --check runs/default/replay",
    "learner": ("romannet learner --config configs/default.toml --run-dir runs/default/learner "
                "--connect tcp/127.0.0.1:7447\n  romannet learner --run-dir runs/default/learner --resume "
                "--connect tcp/127.0.0.1:7447\n  romannet learner --config configs/default.toml --run-dir "
                "runs/offline/learner --offline runs/demo/episodes --max-updates 2000 --set "
                "replay.samples_per_insert=0 --connect tcp/127.0.0.1:7447"),
    "router": ROUTER_EXAMPLE,
    "deploy": DEPLOY_EXAMPLE,
    "actor": ("romannet actor --config configs/default.toml --run-dir runs/default --actor-id actor-0 "
              "--connect tcp/127.0.0.1:7447\n  romannet actor --run-dir runs/default --actor-id actor-1 "
              "--max-actions 50 --set workspace.resolution_m=0.007 --connect tcp/127.0.0.1:7447\n"
              "  romannet actor --robot ur --camera realsense --config robot.toml --run-dir runs/real "
              "--actor-id ur10-0 --connect tcp/10.0.0.5:7447"),
    "calibrate": ("romannet calibrate --config robot.toml --out calibration.json\n"
                  "  romannet calibrate --config robot.toml --set 'calibration.board_offset_m=[0,-0.13,0.02]' "
                  "--out runs/real/calibration.json --report runs/real/calibration.md"),
    "eval": ("romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5 --runs 30\n"
             "  romannet eval runs/clutter --task clutter --objects 30 --object-set novel --protocol frozen\n"
             "  romannet eval runs/clutter --task arrangement"),
    "models": ("romannet models pack runs/clutter --eval runs/clutter/eval/clutter-frozen-20260101-120000 "
               "--out models/clutter\n  romannet models check models/clutter\n"
               "  romannet models check models/clutter --init --config configs/experiments/clutter.toml"),
    "sweep": ("romannet sweep --config configs/experiments/stacking.toml --config "
              "configs/experiments/stacking-baseline.toml --seeds 1 2 3 --max-actions 2500 --out sweeps/stack-abl\n"
              "  romannet sweep --config configs/experiments/clutter.toml --seeds 1 2 --max-actions 2500 "
              "--eval-objects 30 --eval-object-set novel --out sweeps/clutter"),
    "plot": ("romannet plot runs/demo --out demo.png\n"
             "  romannet plot runs/abl-baseline runs/abl-tpg runs/stack-h4 --labels baseline +TPG +TPG+LAE --out abl.png"),
    "analyse": ("romannet analyse pick-offsets runs/stack-h4 --split 20 --json\n"
                "  romannet analyse training-counts runs/stack-h4 --json\n"
                "  romannet analyse angle-probe runs/stack-h4 --episodes 12"),
    "mcap": ("romannet mcap inspect runs/demo/episodes\n  romannet mcap play runs/demo/episodes/actor-0/ep000000.mcap "
             "--foxglove 8765\n  romannet mcap feed runs/demo/episodes --run-id offline-1 --connect "
             "tcp/127.0.0.1:7447\n  romannet mcap export runs/demo/episodes/actor-0/ep000000.mcap --video ep0.mp4\n"
             "  romannet mcap rescore runs/demo/episodes --set reward.push_weight=0.5 --out rescored/"),
}


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE.toml", help="TOML config file (defaults apply to what it omits)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one config value, e.g. --set reward.push_weight=0.5 (repeatable)")


def _load(args: argparse.Namespace):
    from romannet.common.config import load_config

    return load_config(args.config, args.overrides)


def cmd_info(args: argparse.Namespace) -> int:
    from romannet.info import collect_info, format_info

    info = collect_info(_load(args))
    sys.stdout.write((json.dumps(info, indent=2) if args.json else format_info(info)) + "\n")
    return 0


def parse_action(text: str):
    """`primitive:row:col:angle_deg` -> Action (for drawing an action on a snapshot)."""
    import math

    from romannet.common.action import Action

    parts = text.split(":")
    if len(parts) != 4:
        raise ValueError(f"--action {text!r} is invalid: use primitive:row:col:angle_deg, e.g. pick:112:90:30")
    try:
        return Action(parts[0], int(parts[1]), int(parts[2]), math.radians(float(parts[3])), 0.0)
    except ValueError as err:
        raise ValueError(f"--action {text!r} is invalid: {err}") from None


def cmd_sim(args: argparse.Namespace) -> int:
    from romannet.actor.sim.snapshot import write_snapshot

    cfg = _load(args)
    action = parse_action(args.action) if args.action else None
    task = args.task or cfg.task.kind
    out = write_snapshot(task, args.seed if args.seed is not None else cfg.seed, args.out, action=action, sim=cfg.sim)
    log.info("wrote %s", out)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from romannet.replay.main import run

    return run(args)


def cmd_learner(args: argparse.Namespace) -> int:
    from romannet.learner.main import run

    return run(args)


def cmd_actor(args: argparse.Namespace) -> int:
    from romannet.actor.main import run

    if getattr(args, "foxglove", None) is None:
        return run(args)
    # The live view follows the episode files this actor writes, on a thread of its own: the decision path
    # is untouched, and with no client connected a poll reads a few record headers.
    from pathlib import Path

    from romannet.actor.main import resolve_actor_config
    from romannet.actor.service import ActorPaths
    from romannet.common.config import load_config
    from romannet.mcaptools.live import start_live_view

    acfg = resolve_actor_config(load_config(args.config, args.overrides), args)
    folder = ActorPaths.of(Path(args.run_dir), acfg).episodes
    view = start_live_view(lambda: {acfg.actor_id: folder}, args.foxglove, args.foxglove_host,
                           f"actor {acfg.actor_id}")
    try:
        return run(args)
    finally:
        view.close()


def cmd_calibrate(args: argparse.Namespace) -> int:
    from romannet.actor.real.calibrate import run

    return run(args)


def cmd_eval(args: argparse.Namespace) -> int:
    from romannet.evaluate.cli import run

    return run(args)


def cmd_models(args: argparse.Namespace) -> int:
    from romannet.models import run

    return run(args)


def cmd_sweep(args: argparse.Namespace) -> int:
    from romannet.sweep.cli import run

    return run(args)


def cmd_plot(args: argparse.Namespace) -> int:
    from pathlib import Path

    from romannet.evaluate.curves import plot_runs

    if len(args.run_dirs) == 1 and not args.labels:  # one run: its own figure, the one `up` keeps in the run
        from romannet.evaluate.run_curves import summary as curves_summary
        from romannet.evaluate.run_report import RunReport

        run_dir = Path(args.run_dirs[0])
        if not (run_dir / "config.toml").is_file():
            raise RomannetError(f"{run_dir}: not a run directory (it has no config.toml)")
        summary = {"run_dir": str(run_dir), **curves_summary(RunReport(run_dir, args.window, board=False)
                                                               .refresh(Path(args.out)))}
    else:
        summary = plot_runs([Path(d) for d in args.run_dirs], Path(args.out), args.window, args.labels)
    print(json.dumps(summary, indent=1))
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    from romannet.deploy.cli import cmd_router as run

    return run(args)


def cmd_deploy(args: argparse.Namespace) -> int:
    from romannet.deploy.cli import cmd_deploy as run

    return run(args)


def cmd_analyse(args: argparse.Namespace) -> int:
    from romannet.analyse.cli import run

    return run(args)


def cmd_mcap(args: argparse.Namespace) -> int:
    from romannet.mcaptools.cli import run

    return run(args)


def cmd_up(args: argparse.Namespace) -> int:
    from romannet.up import run

    return run(args)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="romannet",
        description="RoManNet fleet: actors, replay server and learner over Eclipse Zenoh.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n" + "\n".join(f"  {v}" for v in EXAMPLES.values()),
    )
    parser.add_argument("--version", action="version", version=f"romannet {__version__}")
    parser.add_argument("--log-level", default=None, help="DEBUG, INFO (default), WARNING or ERROR")
    sub = parser.add_subparsers(dest="verb", required=True, metavar="<verb>")

    def verb(name: str, help_text: str, func: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text,
                           epilog=f"example:\n  {EXAMPLES[name]}", formatter_class=argparse.RawDescriptionHelpFormatter)
        p.set_defaults(func=func)
        return p

    p = verb("up", "run the whole fleet on this machine (replay server, learner, N simulated actors) "
             "under supervision until --max-actions or Ctrl-C; everything goes to runs/<name>/", cmd_up)
    from romannet.up import add_arguments as add_up_arguments  # light imports: --help stays fast

    add_up_arguments(p)
    _add_config_args(p)

    p = verb("info", "version, parameter count per net, torch threads and the resolved config", cmd_info)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _add_config_args(p)

    p = verb("bench", "run a benchmark and print one JSON object (results go in docs/benchmarks.md); "
             "`romannet bench <benchmark> --help` describes one", cmd_bench)
    add_bench_arguments(p)

    p = verb("sim", "simulator tools: `snapshot` writes the camera image and both heightmaps as one PNG", cmd_sim)
    p.add_argument("tool", choices=["snapshot"])
    p.add_argument("--task", choices=["clutter", "arrangement", "stacking"], help="default: the config's task.kind")
    p.add_argument("--seed", type=int, default=None, help="scene seed (default: the config's seed)")
    p.add_argument("--out", required=True, metavar="FILE.png")
    p.add_argument("--action", metavar="PRIM:ROW:COL:DEG", help="draw this action, e.g. pick:112:90:30")
    _add_config_args(p)

    p = verb("replay", "run the prioritized replay server over Zenoh until SIGTERM/SIGINT", cmd_replay)
    _add_config_args(p)
    p.add_argument("--dir", metavar="DIR", help="where the log segments and snapshots live")
    p.add_argument("--check", metavar="DIR", help="read and check every held item of a replay directory, report "
                   "damage and losses, and exit (1 if anything is wrong); writes nothing")
    p.add_argument("--accept-loss", action="store_true",
                   help="start even if recovery finds acknowledged items it cannot get back (they are recorded "
                   "in DIR/losses.json); without it the server refuses to start and names them")
    p.add_argument("--skip-pixel-decode", action="store_true",
                   help="check each PNG's header and chunk CRCs at insert but do not decode its pixels (faster "
                   "inserts; a crafted PNG is then stored and refused by the learner instead); for `romannet "
                   "bench replay`'s comparison")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. a router tcp/10.0.0.2:7447 (repeatable)")
    add_zenoh_config_arg(p)

    p = verb("learner", "train RoManNet from the replay server and publish weights and exploration rates "
             "until SIGTERM/SIGINT (then checkpoint)", cmd_learner)
    _add_config_args(p)
    p.add_argument("--run-dir", required=True, metavar="DIR",
                   help="checkpoints, metrics.csv, TensorBoard events, learning curves and config.toml")
    p.add_argument("--resume", action="store_true",
                   help="continue from the checkpoint in --run-dir (its config.toml unless --config is given)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to: the replay server or a router, e.g. tcp/127.0.0.1:7447")
    add_zenoh_config_arg(p)
    p.add_argument("--offline", action="append", default=[], metavar="FILE|DIR",
                   help="first feed these MCAP episode recordings to the replay server (acknowledged, idempotent), "
                        "then train: without actors, or mixed with live ones (repeatable). A file that is not an "
                        "episode is skipped, of a damaged one every intact chunk is fed, each named in one log "
                        "line; training goes on (check recordings with `romannet mcap inspect --verify`). The "
                        "replay must have no ratio limit (replay.samples_per_insert = 0)")
    p.add_argument("--max-updates", type=int, default=0, metavar="N",
                   help="stop (checkpoint, exit 0) once the learner reaches update N (default: 0 = until a signal)")
    p.add_argument("--init-from", metavar="DIR",
                   help="start a new run from these weights: a model package (models/<experiment>), a run or a "
                        "checkpoint directory (update counter 0, fresh optimiser; the [model] section must match)")

    p = verb("actor", "act in the simulator or on a real robot (UR + RealSense) with the newest weights, send every transition to the replay "
             "server (spooled on disk until acknowledged) and record each episode to MCAP, until "
             "SIGTERM/SIGINT or a limit", cmd_actor)
    _add_config_args(p)
    p.add_argument("--run-dir", required=True, metavar="DIR",
                   help="the run directory: episodes/<actor-id>/*.mcap, actors/<actor-id>/ (spool, status.json)")
    p.add_argument("--actor-id", default=None, metavar="ID",
                   help="this actor's id (default: the config's actor.actor_id); unique within a run")
    p.add_argument("--max-actions", type=int, default=None, metavar="N",
                   help="stop after N actions (default: the config's actor.max_actions; 0 = no limit)")
    p.add_argument("--episodes", type=int, default=None, metavar="N",
                   help="stop after N finished episodes (default: the config's actor.episodes; 0 = no limit)")
    p.add_argument("--foxglove", type=int, metavar="PORT", help="serve this actor's camera, heightmaps, Q maps and "
                   "chosen action live to the Foxglove app on PORT (topics /<actor-id>/...; 0: any free port)")
    p.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address the live view binds (default 127.0.0.1; 0.0.0.0 for other machines)")
    p.add_argument("--robot", choices=("sim", "ur"), default="sim",
                   help="sim: the PyBullet simulator (default); ur: a Universal Robots arm through ur_rtde "
                        "(the [robot] config section; pip install 'romannet[robot]')")
    p.add_argument("--camera", choices=("sim", "realsense"), default=None,
                   help="the camera of a real robot: realsense (default with --robot ur; the [realsense] "
                        "section); sim: the simulator's own")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7449 (repeatable)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to: the replay server or a router, e.g. tcp/127.0.0.1:7447")
    add_zenoh_config_arg(p)

    p = verb("calibrate", "camera-to-robot calibration of a real robot actor: the UR arm moves a checkerboard "
             "on its tool over the [calibration] grid; writes the camera pose and depth scale (the file "
             "robot.calibration_file names) and a Markdown report of the residual per pose; exit 2 if the RMS "
             "residual exceeds calibration.max_rms_error_m", cmd_calibrate)
    _add_config_args(p)
    p.add_argument("--out", default="calibration.json", metavar="FILE.json",
                   help="the calibration file to write (default: calibration.json)")
    p.add_argument("--report", default=None, metavar="FILE.md",
                   help="the Markdown report (default: --out with suffix .md)")

    p = verb("eval", "evaluate a checkpoint with the paper's protocol (30 greedy runs per test case, new seeds; "
             "completion, pick success, action efficiency); writes report.md/.json/.png", cmd_eval)
    from romannet.evaluate.cli import add_arguments as add_eval_arguments

    add_eval_arguments(p)

    p = verb("models", "shipped pretrained policies (models/<experiment>/): `pack` a checkpoint with its eval "
             "report (bf16 weights, config, report, model.json), `check` a package or an --init-from source",
             cmd_models)
    msub = p.add_subparsers(dest="models_cmd", required=True, metavar="<command>")
    pk = msub.add_parser("pack", help="package a run's newest (or one) checkpoint with its evaluation report",
                         description="package a run's newest (or one) checkpoint with its evaluation report; "
                         "refuses to replace a package whose report's completion rate is as good or better",
                         epilog="example:\n  romannet models pack runs/clutter --eval "
                         "runs/clutter/eval/clutter-frozen-20260101-120000 --out models/clutter",
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    pk.add_argument("source", metavar="RUN_OR_CKPT", help="a run directory (newest checkpoint) or a ckpt-* directory")
    pk.add_argument("--eval", dest="eval_dir", required=True, metavar="EVAL_DIR",
                    help="the `romannet eval` output directory of that checkpoint (report.json, report.md)")
    pk.add_argument("--out", required=True, metavar="DIR", help="the package directory, e.g. models/clutter")
    pk.add_argument("--force", action="store_true", help="replace an existing package even if it scored better")
    ck = msub.add_parser("check", help="check a package (files, sha256, tensors), or with --init any weights "
                         "source against a run's config",
                         description="check a package (files, sha256, tensors), or with --init any weights source "
                         "(a package, a run, a checkpoint) against the config a run would train with",
                         epilog="example:\n  romannet models check models/clutter\n  romannet models check "
                         "models/clutter --init --config configs/experiments/clutter.toml",
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    ck.add_argument("path", metavar="DIR", help="a model package, or with --init also a run or a checkpoint")
    ck.add_argument("--init", action="store_true",
                    help="check DIR as an --init-from source for a run with --config/--set (default config)")
    _add_config_args(ck)

    p = verb("sweep", "train every recipe (--config, repeatable) with every seed one run after another, evaluate "
             "each frozen on the same scenes beside the oracle and random policies, and write the mean, min and "
             "max over seeds to <out>/results.md/.json and curves.png; the same command resumes it", cmd_sweep)
    from romannet.sweep.cli import add_arguments as add_sweep_arguments

    add_sweep_arguments(p)

    p = verb("plot", "learning curves over training actions into one PNG: of one run, action success and "
             "efficiency, episode completion, return and length, actions per second (the run's own "
             "training_curves.png); of several, action success and efficiency, one line per run or per label "
             "shared by several runs (their mean and range)", cmd_plot)
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR")
    p.add_argument("--out", required=True, metavar="FILE.png")
    p.add_argument("--window", type=int, default=200, metavar="N", help="sliding window in actions (200)")
    p.add_argument("--labels", nargs="+", metavar="LABEL",
                   help="one label per run (default: directory names); runs given the same label are seeds of "
                   "one variant, drawn as their mean with a min-max band")

    p = verb("router", "run a Zenoh router (zenoh-python in router mode) for a multi-machine fleet until "
             "SIGTERM/SIGINT; the same config files work with zenohd (docs/deploy.md)", cmd_router)
    add_router_arguments(p)

    p = verb("deploy", "multi-machine set-up: `certs` (a CA, per-role certificates and secure Zenoh configs), "
             "`configs` (Zenoh configs only), `check` (is every role of a run reachable?)", cmd_deploy)
    add_deploy_arguments(p)

    from romannet.mcaptools.cli import SUMMARY as MCAP_SUMMARY
    from romannet.mcaptools.cli import add_arguments as add_mcap_arguments

    add_mcap_arguments(verb("mcap", MCAP_SUMMARY, cmd_mcap))

    from romannet.analyse.cli import SUMMARY as ANALYSE_SUMMARY
    from romannet.analyse.cli import add_arguments as add_analyse_arguments

    add_analyse_arguments(verb("analyse", ANALYSE_SUMMARY, cmd_analyse))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parse_args(parser, argv)
    try:
        setup_logging(args.log_level)
        return args.func(args)
    except RomannetError as err:
        # Expected failures (bad config, bad input) get one clear line, not a traceback.
        sys.stderr.write(f"romannet {args.verb}: error: {err}\n")
        return 2
    except ValueError as err:
        sys.stderr.write(f"romannet {args.verb}: error: {err}\n")
        return 2
    except OSError as err:
        if err.filename is None:
            raise
        # A path the command cannot use (a file where a directory belongs, no permission, a full disk):
        # one line naming it, as for any other bad input.
        sys.stderr.write(f"romannet {args.verb}: error: {os_error_line(err)}\n")
        return 2


def os_error_line(err: OSError) -> str:
    """'PATH: what is wrong' for an OSError that names a path."""
    hint = ""
    if isinstance(err, FileExistsError | NotADirectoryError):
        hint = " (a file stands where a directory is needed)"
    return f"{err.filename}: {err.strerror or err}{hint}"


if __name__ == "__main__":
    sys.exit(main())
