"""`romannet bench <benchmark>`: the benchmarks' sub-commands (each with only the options it reads) and
their dispatch. Apart from romannet/cli.py so the verb table stays short; like every verb, a benchmark's
module is imported only when it runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from romannet.bench.system import OPTIONAL_PARTS, SYSTEM_PARTS


def _repeats(args: argparse.Namespace) -> dict:
    """Each benchmark has its own default repeat count; pass --repeats only when the user gave it."""
    return {} if args.repeats is None else {"repeats": args.repeats}


def _numbers(text: str, option: str, kind: type, count: int | None = None) -> list:
    """Comma-separated numbers of an option; ValueError (one line at the CLI) naming the option."""
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or (count is not None and len(values) != count):
        raise ValueError(f"{option} {text!r}: expected {count or 'one or more'} comma-separated "
                         f"{kind.__name__} value(s), e.g. {'1,2' if count == 2 else '8,32,64'}")
    return values


def _hands_sizes_robot(args: argparse.Namespace) -> tuple[tuple[str, ...], tuple[float, ...], str]:
    """The geometry benchmarks' --hands and --cube-sizes lists, and the robot mode (the last of --robots)."""
    hands = tuple(h.strip() for h in args.hands.split(",") if h.strip())
    sizes = tuple(float(c) for c in args.cube_sizes.split(",") if c.strip())
    return hands, sizes, args.robots.split(",")[-1].strip()


def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "inference":
        from romannet.bench.inference import run_inference_benchmark

        result = run_inference_benchmark(seed=args.seed, **_repeats(args))
    elif args.what == "replay":
        from romannet.bench.replay import run_replay_benchmark

        result = run_replay_benchmark(inserts=args.inserts, seed=args.seed, **_repeats(args))
    elif args.what == "sim":
        from romannet.bench.sim import run_sim_benchmark

        robots = tuple(r.strip() for r in args.robots.split(",") if r.strip())
        result = run_sim_benchmark(actions=args.actions, seed=args.seed, robots=robots)
    elif args.what == "learner":
        from romannet.bench.learner import run_learner_benchmark

        sizes = tuple(int(b) for b in args.batch_sizes.split(",") if b.strip())
        result = run_learner_benchmark(batch_sizes=sizes, seed=args.seed, device=args.device, threads=args.threads,
                                       **_repeats(args))
    elif args.what == "system":
        from romannet.bench.system import run_system_benchmark

        parts = tuple(x.strip() for x in args.parts.split(",") if x.strip())
        result = run_system_benchmark(actions_per_actor=args.actions, seed=args.seed, parts=parts,
                                      late_from=args.late_from, **_repeats(args))
    elif args.what == "pick-geometry":
        from romannet.bench.pick_geometry import markdown, run_pick_geometry_benchmark

        hands, sizes, robot = _hands_sizes_robot(args)
        result = run_pick_geometry_benchmark(hands=hands, cube_sizes_m=sizes, robot=robot, seed=args.seed)
        result["markdown"] = markdown(result)
    elif args.what == "place-geometry":
        from romannet.bench.place_geometry import markdown as place_markdown
        from romannet.bench.place_geometry import run_place_geometry_benchmark

        hands, sizes, robot = _hands_sizes_robot(args)
        result = run_place_geometry_benchmark(hands=hands, cube_sizes_m=sizes, robot=robot,
                                              seeds=(args.seed, args.seed + 1))
        result["markdown"] = place_markdown(result)
    elif args.what == "fuzz":
        from romannet.bench.fuzz import FuzzPlan, run_fuzz

        big = tuple(int(m) for m in args.big_mb.split(",") if m.strip())
        result = run_fuzz(FuzzPlan(messages=args.messages, big_mb=big, seed=args.seed))
    elif args.what == "chaos":
        from romannet.bench.chaos import ChaosPlan, run_chaos

        low, high = (float(x) for x in args.kill_every.split(","))
        result = run_chaos(ChaosPlan(duration_s=args.duration, kill_every_s=(low, high), flips=args.flips,
                                     seed=args.seed))
    elif args.what == "fleet":
        from romannet.bench.fleet import FleetPlan, run_fleet_benchmark

        low, high = _numbers(args.period, "--period", float, 2)
        plan = FleetPlan(sizes=tuple(_numbers(args.sizes, "--sizes", int)), duration_s=args.duration,
                         period_s=(low, high), topology=args.topology, settings=tuple(args.set), seed=args.seed)
        result = run_fleet_benchmark(plan)
    elif args.what == "faults":
        from romannet.bench.faults import run_fault_scenario_checked

        result = run_fault_scenario_checked()
    else:  # argparse choices make this unreachable; kept explicit for the error message
        raise SystemExit(f"unknown benchmark {args.what!r}")
    text = json.dumps(result, indent=None if args.json else 2)
    sys.stdout.write(text + "\n")
    return 1 if result.get("ok") is False else 0


# Each benchmark: (one line for the list, what it measures for its --help, its example, the options it reads
# besides --json).
BENCHMARKS: dict[str, tuple[str, str, str, tuple[str, ...]]] = {
    "inference": ("the actor's decision latency against baselines",
                  "The actor's decision latency (forward passes of the three nets and the choice of action) "
                  "against the naive eager fp32 baselines.", "romannet bench inference --json", ("seed", "repeats")),
    "replay": ("durable inserts/s, sample latency, recovery time, cost of the pixel check",
               "The replay server over loopback Zenoh: durable inserts per second, sample latency, the time "
               "to recover --inserts transitions from its log, and what decoding every PNG at insert costs "
               "(the same inserts into a server started with --skip-pixel-decode).",
               "romannet bench replay --json --inserts 2000 --repeats 200", ("seed", "repeats", "inserts")),
    "sim": ("simulator actions/s per task, ms per render, heightmap and primitive",
            "The simulator: actions per second per task, and milliseconds per render, heightmap and primitive, "
            "for each robot mode.", "romannet bench sim --json --actions 10 --robots arm,gripper",
            ("seed", "actions", "robots")),
    "learner": ("transitions trained/s per batch size",
                "Transitions trained per second for each batch size: the learner's step against the same with "
                "the last conv on the whole window, the whole-map step and the naive eager fp32 step.",
                "romannet bench learner --json --batch-sizes 4 --repeats 5 --threads 1",
                ("seed", "repeats", "batch_sizes", "device", "threads")),
    "system": ("fleet actions/s, weights latency, where actor time goes",
               "The whole fleet (`romannet up`): actions per second with 1 and 2 gripper actors, weights "
               "latency to 1 and 8 actors, the clutter recipe's training pace (today's learner path against the "
               "whole-map one; the actor's precision \"auto\" against fp32) and the share of actor time in "
               "simulation, inference, encoding and transport.", "romannet bench system --json --actions 30",
               ("seed", "repeats", "actions", "parts")),
    "pick-geometry": ("which picks of a lone cube each hand holds",
                      "Which picks of a lone cube each simulated hand holds, by offset from the cube's centre "
                      "and by angle.", "romannet bench pick-geometry --hands panda,rg2 --cube-sizes 0.05,0.04",
                      ("seed", "robots", "hands", "cube_sizes")),
    "place-geometry": ("which places of a held cube onto a stack hold, fingers coupled or not",
                       "Which places of a cube picked at its centre onto a lone cube and a 2-stack hold, by offset "
                       "from the top's centre and by turn, with the fingers coupled (sim.coupled_fingers) and "
                       "independent; two worlds (--seed and the next) and two offset directions per cell.",
                       "romannet bench place-geometry --hands panda,rg2 --cube-sizes 0.04",
                       ("seed", "robots", "hands", "cube_sizes")),
    "fuzz": ("2,000 malformed and 100 MB-1 GB messages at a replay server, and its memory",
             "A real replay server over loopback Zenoh takes --messages bad messages (random bytes, flipped and "
             "cut transitions, wrong keys, garbage requests, transitions just over replay.max_item_bytes and "
             "--big-mb messages far over every limit); it prints the refusals by reason, the server's resident "
             "memory before and at its peak (their ratio must stay <= 2), whether it still answers and holds "
             "exactly its good items, and its exit code. About 30 s and 2 GB in this process for a 1 GB message. "
             "Exit 1 if a check fails.", "romannet bench fuzz --json --messages 2000 --big-mb 100,250,500,1000",
             ("seed", "messages", "big_mb")),
    "chaos": ("2 actors for 10 min while random children are SIGKILLed; lost, duplicated, memory",
              "A fleet of 2 actors (replay server, learner, actor-0, actor-1 as processes on loopback Zenoh; a "
              "tiny model, 64x64 heightmaps) trains for --duration seconds while every 30-90 s (--kill-every) "
              "one random child (each once per round of four) is killed with SIGKILL and restarted at once (the learner with --resume), and "
              "after each kill --flips bytes are flipped in a copy of the replay directory, which is then "
              "checked as `romannet replay --check` does. It prints actions, acknowledged, stored, lost and "
              "duplicated (the replay's durable log read back at the end), per replay kill the items the server "
              "held just before and recovered after, per damaged copy what was recovered, reported "
              "damaged, reported lost and unreported, and each service's peak RSS in each half of the run. "
              "Exit 1 unless 0 lost, 0 duplicated, nothing unreported, memory flat (second-half peak <= 1.5x "
              "the first) and every process stopped cleanly. Not a test: run it niced on a shared machine.",
              "romannet bench chaos --json --duration 600 --kill-every 30,90 --flips 8",
              ("seed", "duration", "kill_every", "flips")),
    "fleet": ("weights fan-out, learner egress, inserts and updates/s with 8, 32, 64 light actors",
              "One learner, one replay server and N light actors (no physics, no model: the actor's weights "
              "source, spool and sender, one synthetic transition every 1-2 s) through a `romannet router`, "
              "real processes, each in a network namespace of its own when run as root (else on loopback), "
              "a fresh fleet per size of --sizes, after a 1-actor run. Per size, over --duration seconds once "
              "every actor holds weights: weights from the learner's publish call to every actor (median, "
              "p99), the learner's bytes out per version (and in copies of the weights), inserts/s and insert "
              "p50/p99 at the actors, the learner's sample p50/p99 and updates/s (and its ratio to the 1-actor "
              "run), the actors' CPU and memory, and the ledger: produced, acknowledged, stored, lost, "
              "duplicated. --set takes config overrides (e.g. learner.weights_wire_dtype=\"fp32\"). About "
              "(--duration + 1 min) per size; 8, 32, 64 at 180 s take ~20-25 min on an idle machine. Exit 1 if a "
              "transition is lost or duplicated, an actor never got the weights or a process did not stop "
              "cleanly. Not a test: run it on an idle machine.",
              "sudo romannet bench fleet --json --sizes 8,32,64 --duration 180",
              ("seed", "sizes", "duration", "period", "topology", "set")),
    "faults": ("a secure multi-host fleet through kill -9, a cut link and an intruder (root)",
               "A secure fleet on five Linux network-namespace hosts (a router; the replay server and the "
               "learner; two actors; an operator), with the configs `romannet deploy certs` writes: mutual TLS, "
               "access control denying by default. During one short training run it tries an intruder with "
               "actor-0's certificate and clients with no certificate or another CA's, kills the replay "
               "server, the learner (restarted with --resume) and an actor with SIGKILL, and cuts one actor's "
               "link for 10 s. It prints each fault's recovery time, each access-control check, and the "
               "transitions sent, acknowledged, stored, lost and duplicated. Needs root (ip netns) and about "
               "a minute. Exit 1 if a transition is lost or duplicated, something is allowed that must be "
               "denied, or a process does not stop cleanly.", "sudo romannet bench faults --json", ()),
}


def add_bench_arguments(p: argparse.ArgumentParser) -> None:
    """One sub-command per benchmark, each with its description, example and only the options it reads."""
    import textwrap

    sub = p.add_subparsers(dest="what", required=True, metavar="<benchmark>")
    for name, (short, what, example, options) in BENCHMARKS.items():
        q = sub.add_parser(name, help=short, description=textwrap.fill(what, 100),
                           epilog=f"example:\n  {example}", formatter_class=argparse.RawDescriptionHelpFormatter)
        q.add_argument("--json", action="store_true", help="print compact JSON on one line")
        # cmd_bench reads every field; a benchmark without the option gets its default.
        q.set_defaults(seed=0, repeats=None, inserts=2000, actions=10, robots="arm,gripper", hands="panda,rg2",
                       cube_sizes="0.05,0.04", batch_sizes="1,4,8", device="cpu", messages=2000,
                       big_mb="100,250,500,1000", duration=600.0, kill_every="30,90", flips=8,
                       sizes="8,32,64", period="1,2", topology="auto", set=[], parts=",".join(SYSTEM_PARTS),
                       threads=0, late_from=None)
        if "seed" in options:
            q.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
        if "repeats" in options:
            q.add_argument("--repeats", type=int, default=None,
                           help="timed repeats per measurement (median reported); default: the benchmark's own")
        if "inserts" in options:
            q.add_argument("--inserts", type=int, default=2000, help="transitions inserted (and recovered)")
        if "actions" in options:
            q.add_argument("--actions", type=int, default=10,
                           help="actions per task and policy" if name == "sim" else "actions per actor")
        if "robots" in options:
            q.add_argument("--robots", default="arm,gripper",
                           help="comma-separated robot modes (arm, gripper)" if name == "sim"
                           else "the robot mode (arm or gripper; the last of a comma-separated list)")
        if "hands" in options:
            q.add_argument("--hands", default="panda,rg2", help="comma-separated sim.hand values")
        if "cube_sizes" in options:
            q.add_argument("--cube-sizes", default="0.05,0.04", help="comma-separated cube edges (m)")
        if "batch_sizes" in options:
            q.add_argument("--batch-sizes", default="1,4,8", help="comma-separated transitions per update")
        if "messages" in options:
            q.add_argument("--messages", type=int, default=2000, help="bad messages sent, the big ones included")
        if "big_mb" in options:
            q.add_argument("--big-mb", default="100,250,500,1000",
                           help="comma-separated sizes (MB) of the messages far over every limit")
        if "duration" in options and name == "fleet":
            q.add_argument("--duration", type=float, default=180.0, help="measured seconds per fleet size, "
                           "once every actor holds weights (default 180)")
        elif "duration" in options:
            q.add_argument("--duration", type=float, default=600.0, help="seconds of chaos once the fleet is up")
        if "parts" in options:
            q.add_argument("--parts", default=",".join(SYSTEM_PARTS), metavar="PART,...",
                           help=f"comma-separated measurements, of {', '.join(SYSTEM_PARTS)} (default: all) "
                           f"and {', '.join(OPTIONAL_PARTS)} (a finished run resumed for 250 actions, the "
                           "learner's defaults against staler V(s') and weights every other update; needs "
                           "--late-from)")
            q.add_argument("--late-from", type=Path, default=None, metavar="RUN_DIR",
                           help="a finished `romannet up` run of the clutter recipe for part 'late' (copied; "
                           "the run itself is not touched)")
        if "sizes" in options:
            q.add_argument("--sizes", default="8,32,64", help="comma-separated numbers of light actors "
                           "(default 8,32,64; a 1-actor run comes first)")
        if "period" in options:
            q.add_argument("--period", default="1,2", metavar="LOW,HIGH",
                           help="seconds between an actor's transitions, uniform in [LOW, HIGH] (default 1,2)")
        if "topology" in options:
            q.add_argument("--topology", choices=("auto", "netns", "loopback"), default="auto",
                           help="netns: a network namespace per process (root); loopback: all on 127.0.0.1; "
                           "auto: netns where possible (default)")
        if "set" in options:
            q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                           help="config override for the whole fleet (repeatable), e.g. model.channels=16")
        if "kill_every" in options:
            q.add_argument("--kill-every", default="30,90", metavar="LOW,HIGH",
                           help="seconds between kills, drawn uniformly from [LOW, HIGH]")
        if "flips" in options:
            q.add_argument("--flips", type=int, default=8, help="bytes flipped in each damaged copy")
        if "threads" in options:
            q.add_argument("--threads", type=int, default=0,
                           help="torch threads (default 0: one per core; `romannet up` gives a learner beside one "
                                "actor on 2 cores 1)")
        if "device" in options:
            q.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (when there is a GPU)")
