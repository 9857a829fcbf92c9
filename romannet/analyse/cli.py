"""`romannet analyse <what> RUN`: the run diagnostics' command line (romannet/cli.py adds the verb).

Only the standard library is imported at the top, so `romannet --help` stays fast; a diagnostic's module is
imported when it runs. Each prints one JSON object (--json) or a line per phase (per part for angle-probe);
bad input (a missing run, a file that is not an episode, no checkpoint) is one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from collections.abc import Callable
from functools import partial
from pathlib import Path

SUMMARY = ("diagnose a run from its recorded episodes: where picks land, where a stacking run's actions go, "
           "repeated failures, training counts, what the pick angle head learned; `romannet analyse <what> "
           "--help` describes one")

# Each diagnostic: (one line for the list, what it reports for its --help, its examples).
DIAGNOSTICS: dict[str, tuple[str, str, str]] = {
    "pick-offsets": (
        "where the picks land on the objects: offset from the centre along and across the closing axis, "
        "angle to the faces",
        "Where a run's picks land on the objects. A parallel-jaw pick of a box-like object succeeds when the "
        "fingers straddle it, so the pick pixel must be near the object's centre along the closing axis. For "
        "every recorded pick, the object under (or within 8 px of) its pixel is the connected blob of "
        "heightmap pixels above --min-height; against the blob's minimum-area rectangle, the pick's offset "
        "from the centre along and across the closing axis and the angle between the closing axis and the "
        "faces (0-45 deg) are measured. Per training phase, greedy and explored picks apart: picks, "
        "successes, the median offsets and angles of successful and failed picks, and the mean cos 4(angle "
        "to the faces) (1 = square to the faces, -1 = on the diagonal, 0 = no preference). Blobs larger than "
        "--max-area-cm2 (stacks, touching objects) are counted but left out of the medians.",
        "romannet analyse pick-offsets runs/stack-h4 --split 20 --json"),
    "stack-actions": (
        "a stacking run's picks and places: on the table, on a lone cube or on a stack's top",
        "Where a stacking run's picks and places land. The TPG reward gives 0 to an action that reverses "
        "progress, so a policy should learn not to pick cubes off its stack and to place on its top. For every "
        "recorded pick and place: the stack height before it (as the simulator's reward measures it) and the "
        "cubes under the action pixel (the tallest point within --radius-m of it, in cube heights of the "
        "recorded task.cube_size_m). Per training phase, greedy and explored apart: attempts and successes by "
        "(stack height, cubes under the pixel), and, while a stack of 2 or more stood, how many greedy picks "
        "went to a stack's top (and took a cube off it) and how many greedy places went there (and raised it). "
        "For greedy places: the median distance from the centre of the cube top under the pixel, of those that "
        "succeeded and those that failed, and how many went onto a lower cube while a stack of 2 or more stood "
        "and how far that stack was (the nets' receptive field reaches 11 cm either side of a pixel).",
        "romannet analyse stack-actions runs/stack-h4 --split 5 --json"),
    "repeated-failures": (
        "how often the greedy policy repeats the action that just failed",
        "How often the greedy policy repeats the action that just failed. A failed pick or push leaves the "
        "scene as it was, so a greedy policy whose weights have not changed picks the same pixel again. From "
        "the recorded /step records, per training phase: the greedy actions right after a failure, how many "
        "repeat it exactly (same primitive and pixel), and how many of those ran on the same weights version.",
        "romannet analyse repeated-failures runs/clutter --split 52 --json"),
    "grasp-failures": (
        "why a simulated run's picks failed: by cause, by the object's tilt and the grasp's offset",
        "Why a simulated run's picks failed, from the simulator's ground truth recorded with each pick (its "
        "/step record's info): after the fingers closed, did they close on nothing, on two objects, or hold one "
        "that was lost in the lift; and for an object both fingers touched, its tilt and how far its centre of "
        "mass lies from the pick's point across the closing axis (the lever it turns about the fingers with). "
        "Per training phase: picks, failures by cause, and the share failed by tilt and by that offset.",
        "romannet analyse grasp-failures runs/clutter --split 100 --json"),
    "training-counts": (
        "actions, pick and place success, explored actions, success per block, episodes, highest stacks",
        "A training run's counts: actions, attempts and successes per primitive, explored actions, successful "
        "actions per block of --block actions in order, action success over the last --last actions, "
        "episodes, completed ones and how each ended, and for stacking the highest stack each episode "
        "reached. All actors together, in order of each action's end time.",
        "romannet analyse training-counts runs/stack-h4 --json\n"
        "  romannet analyse training-counts runs/clutter --block 100 --last 250"),
    "angle-probe": (
        "what a checkpoint's pick angle head says at lone cubes and at the picks it was trained on",
        "What a checkpoint's pick rotation head says about cubes, asked of recorded scenes. At the centre of "
        "each lone cube in the first state of each probed episode: the head's closing axis against the "
        "cube's faces (mean cos 4(angle): 1 = square to every cube, -1 = on every diagonal). At the recorded "
        "successful picks, greedy and explored apart: the head's angle against the executed one, modulo 90 "
        "deg. Agreement at the picks but not at the cubes = the head fits the picks it was trained on and "
        "does not carry that to other cubes. Reads the run's config.toml, a checkpoint (default: the latest) "
        "and up to --episodes episode files spread over the run.",
        "romannet analyse angle-probe runs/stack-h4 --episodes 12 --json\n"
        "  romannet analyse angle-probe runs/stack-h4 --checkpoint runs/stack-h4/checkpoints/ckpt-000001000"),
}


def _at_least(low: float, kind: Callable[[str], float]) -> Callable[[str], float]:
    """An argparse type: `kind`(text), refused below `low` (NaN too) with a message naming the bound."""
    def parse(text: str) -> float:
        value = kind(text)
        if not value >= low:
            raise argparse.ArgumentTypeError(f"must be at least {low}; got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse's "invalid int value" for text that is not a number
    return parse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """One sub-command per diagnostic, each with its description, example and only the options it reads."""
    sub = p.add_subparsers(dest="what", required=True, metavar="<what>")
    parsers = {name: sub.add_parser(name, help=short, description=textwrap.fill(what, 100),
                                    epilog=f"example:\n  {example}",
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
               for name, (short, what, example) in DIAGNOSTICS.items()}
    for name, q in parsers.items():
        if name == "angle-probe":
            q.add_argument("run_dir", metavar="RUN",
                           help="a run directory: its config.toml, checkpoints/ and episodes/")
        else:
            q.add_argument("run_dir", metavar="RUN",
                           help="a run directory (its episodes/), a directory of episode files, or one file")
            q.add_argument("--split", type=int, default=0, metavar="N",
                           help="first episode index of the second phase (default 0: one phase)")
        q.add_argument("--json", action="store_true", help="print one JSON object")
    for name in ("pick-offsets", "angle-probe"):
        parsers[name].add_argument("--min-height", type=float, default=0.02, metavar="M",
                                   help="object pixels are higher than this (m; default 0.02)")
    parsers["pick-offsets"].add_argument("--max-area-cm2", type=float, default=35.0, metavar="CM2",
                                         help="larger blobs (stacks, touching objects) are left out of the "
                                         "medians (default 35)")
    parsers["stack-actions"].add_argument("--radius-m", type=_at_least(0.0, float), default=0.005, metavar="M",
                                          help="cubes under an action: the tallest point within this distance "
                                          "of its pixel (m; default 0.005)")
    counts = parsers["training-counts"]
    counts.add_argument("--block", type=_at_least(1, int), default=50, metavar="N",
                        help="actions per block of the successful-action counts (default 50)")
    counts.add_argument("--last", type=_at_least(1, int), default=500, metavar="N",
                        help="action success over this many last actions (default 500)")
    probe = parsers["angle-probe"]
    probe.add_argument("--checkpoint", metavar="DIR", help="a ckpt-* directory (default: the run's latest)")
    probe.add_argument("--episodes", type=_at_least(1, int), default=12, metavar="N",
                       help="episodes probed, spread evenly over the run (default 12)")


def _result(args: argparse.Namespace) -> dict:
    """The chosen diagnostic's result for args.run_dir."""
    run_dir = Path(args.run_dir)
    if args.what == "angle-probe":
        from .angle_probe import probe_run

        checkpoint = Path(args.checkpoint) if args.checkpoint else None
        return probe_run(run_dir, checkpoint, args.episodes, args.min_height)
    per_phase: Callable[[list[Path]], dict]
    if args.what == "pick-offsets":
        from .pick_offsets import phase_summary

        per_phase = partial(phase_summary, min_height_m=args.min_height, max_area_cm2=args.max_area_cm2)
    elif args.what == "stack-actions":
        from .stack_actions import phase_summary

        per_phase = partial(phase_summary, radius_m=args.radius_m)
    elif args.what == "grasp-failures":
        from .grasp_failures import phase_summary as grasp_summary

        per_phase = grasp_summary
    elif args.what == "repeated-failures":
        from .repeated_failures import phase_counts

        per_phase = phase_counts
    else:
        from .training_counts import phase_summary

        per_phase = partial(phase_summary, block=args.block, last=args.last)
    from .phases import by_phase

    return by_phase(run_dir, args.split, per_phase)


def run(args: argparse.Namespace) -> int:
    """Run the diagnostic named in args.what and print its result; 2 with one line on stderr for bad input."""
    from romannet.common.errors import RomannetError

    try:
        out = _result(args)
    except (RomannetError, OSError, ValueError) as err:
        sys.stderr.write(f"romannet analyse {args.what}: error: {err}\n")
        return 2
    text = json.dumps(out, indent=2) if args.json else "\n".join(f"{k}: {v}" for k, v in out.items())
    sys.stdout.write(text + "\n")
    return 0
