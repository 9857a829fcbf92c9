"""`romannet mcap <tool>`: the command line of the episode-file tools (romannet/cli.py adds the verb).

Only the standard library is imported at the top, so `romannet --help` stays fast; each tool's module is
imported when it runs.
"""

from __future__ import annotations

import argparse
import sys

EXAMPLES = {
    "inspect": "romannet mcap inspect runs/demo/episodes --json",
    "play": ("romannet mcap play runs/demo/episodes/actor-0/ep000000.mcap --foxglove 8765 --speed 2\n"
             "  romannet mcap play ep000000.mcap --zenoh --speed 0 --connect tcp/127.0.0.1:7447"),
    "live": ("romannet mcap live runs/demo/episodes --foxglove 8765\n"
             "  romannet mcap live runs/demo/episodes/actor-0 --foxglove 8765 --foxglove-host 0.0.0.0"),
    "feed": "romannet mcap feed runs/demo/episodes --run-id offline-1 --connect tcp/127.0.0.1:7447",
    "export": ("romannet mcap export runs/demo/episodes/actor-0/ep000000.mcap --video ep0.mp4\n"
               "  romannet mcap export ep000000.mcap --frames frames/ --size 224"),
    "rescore": ("romannet mcap rescore runs/demo/episodes --set reward.push_weight=0.5 --out rescored/\n"
                "  romannet mcap rescore runs/demo/episodes --reward-config new_reward.toml --feed --run-id "
                "offline-1 --connect tcp/127.0.0.1:7447"),
}
SUMMARY = ("episode files (MCAP): inspect them, play them to Foxglove or Zenoh, feed them to a replay server, "
           "export video, rescore them under another reward; format in docs/recording.md")


def _foxglove_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--foxglove", type=int, metavar="PORT", help="serve a Foxglove WebSocket on PORT (0: any free)")
    p.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address the Foxglove server binds (default 127.0.0.1; 0.0.0.0 for other machines)")


def _zenoh_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (repeatable; default: a free loopback port)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to: the replay server or a router, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-config", metavar="FILE.json5",
                   help="Zenoh config file (default: peer mode on loopback, multicast scouting off)")


def _feed_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run-id", metavar="RUN", help="the replay server's run id (default: the run the files were "
                   "recorded in)")
    p.add_argument("--window", type=int, default=4, metavar="N", help="inserts in flight at once (default: 4)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S", help="deadline of one insert (default: 10)")
    p.add_argument("--give-up-after", type=float, default=120.0, metavar="S",
                   help="retry one transition through outages this long before stopping (default: 120)")
    p.add_argument("--wait", type=float, default=30.0, metavar="S",
                   help="wait this long for the replay server to appear (default: 30)")
    _zenoh_args(p)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The `mcap` verb's sub-commands."""
    sub = p.add_subparsers(dest="tool", required=True, metavar="<tool>")

    def tool(name: str, help_text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help_text, description=help_text, epilog=f"example:\n  {EXAMPLES[name]}",
                              formatter_class=argparse.RawDescriptionHelpFormatter)

    t = tool("inspect", "per episode: task, actor, seed, steps, actions and successes by primitive, rewards, end "
             "reason, weights versions, duration, file health (a truncated file is read up to its last whole "
             "chunk; in a damaged one each damaged chunk or record is named and skipped and the rest is read). "
             "Every file is reported; exit code 1 if any file is not an episode, is damaged or holds invalid "
             "transitions (each named in one line on stderr), 0 otherwise")
    t.add_argument("inputs", nargs="+", metavar="FILE|DIR", help="episode files, or directories of *.mcap")
    t.add_argument("--json", action="store_true", help="print one JSON object")
    t.add_argument("--verify", action="store_true",
                   help="decode and validate every transition (pixels too), as the replay server and learner do; "
                   "exit code 1 also for a file that is truncated or unfinished")

    t = tool("play", "play an episode back in recorded order and time to a Foxglove WebSocket server and/or on "
             "the actor's live Zenoh keys (romannet/@v1/<run>/actor/<actor>/live/<topic>)")
    t.add_argument("file", metavar="FILE")
    t.add_argument("--speed", type=float, default=1.0, metavar="X", help="playback rate (default 1; 0: no waiting)")
    t.add_argument("--max-gap", type=float, default=5.0, metavar="S",
                   help="shorten pauses in the recording to at most S seconds (default: 5)")
    t.add_argument("--loop", action="store_true", help="play again from the start until Ctrl-C")
    _foxglove_args(t)
    t.add_argument("--wait-client", type=float, default=60.0, metavar="S",
                   help="with --foxglove: wait up to S s for the app to subscribe before playing (-1: "
                        "until it does, 0: do not wait; default: 60)")
    t.add_argument("--zenoh", action="store_true", help="publish on Zenoh as the actor would, live")
    t.add_argument("--run-id", metavar="RUN", help="with --zenoh: run id of the keys (default: the recorded one)")
    t.add_argument("--actor-id", metavar="ID", help="with --zenoh: actor id of the keys (default: the recorded one)")
    t.add_argument("--zenoh-wait", type=float, default=2.0, metavar="S",
                   help="with --zenoh: wait up to S s for a subscriber to match before playing (default: 2)")
    _zenoh_args(t)

    t = tool("live", "serve the episodes being written to the Foxglove app, live: a run's episodes/ directory "
             "(every actor, on /<actor_id>/<topic>) or one actor's folder; until Ctrl-C")
    t.add_argument("folder", metavar="DIR", help="<run>/episodes, or <run>/episodes/<actor_id>")
    _foxglove_args(t)

    t = tool("feed", "send the recorded transitions to a running replay server, acknowledged, with a progress "
             "bar; feeding the same files again adds nothing (idempotent keys). A file that is not an episode "
             "is skipped, of a damaged one every intact chunk is fed, of a truncated one all up to its last "
             "whole chunk; exit code 1 if a file was skipped or damaged (each named in one line on stderr) or "
             "a transition rejected, 0 otherwise")
    t.add_argument("inputs", nargs="+", metavar="FILE|DIR")
    t.add_argument("--json", action="store_true", help="print one JSON object")
    _feed_args(t)

    t = tool("export", "a video or PNG frames for people: camera image, heightmaps (one with the Q map, one "
             "with its depth colour bar) seen from above with the action, reward and success")
    t.add_argument("file", metavar="FILE")
    t.add_argument("--video", metavar="OUT.mp4", help="write an H.264 mp4 (PyAV, plays in browsers), one frame per step")
    t.add_argument("--frames", metavar="DIR", help="write one PNG per step (step_00000.png, ...)")
    t.add_argument("--fps", type=float, default=2.0, help="video frames (steps) per second (default: 2)")
    t.add_argument("--size", type=int, default=448, metavar="PX", help="height of the image panels (default: 448)")

    t = tool("rescore", "recompute X, P and rewards from the recorded heightmaps under another reward "
             "configuration; write new episode files (--out) and/or feed them (--feed)")
    t.add_argument("inputs", nargs="+", metavar="FILE|DIR")
    t.add_argument("--reward-config", metavar="FILE.toml", help="a TOML file whose [reward] table changes the "
                   "recorded reward configuration (a whole fleet config works too)")
    t.add_argument("--set", dest="overrides", action="append", default=[], metavar="reward.FIELD=VALUE",
                   help="change one reward field, e.g. --set reward.push_weight=0.5 (repeatable)")
    t.add_argument("--success", choices=["auto", "heightmap", "recorded"], default="auto",
                   help="X: auto (default) = push and place from the heightmaps, pick as the gripper recorded "
                        "it; heightmap = all from the heightmaps; recorded = all as recorded")
    t.add_argument("--changed-height", type=float, default=0.01, metavar="M",
                   help="heightmap X: a pixel changed when its height moved more than M metres (default 0.01)")
    t.add_argument("--push-area", type=float, default=5e-4, metavar="M2",
                   help="heightmap X of a push: at least this area changed height, m^2 (default 5e-4)")
    t.add_argument("--pick-area", type=float, default=3e-4, metavar="M2",
                   help="heightmap X of a pick: the occupied area shrank at least this much, m^2 (default 3e-4)")
    t.add_argument("--out", metavar="DIR", help="write the rescored episodes to DIR/<run>/<actor>/<episode>.mcap")
    t.add_argument("--feed", action="store_true", help="send the rescored transitions to a replay server")
    t.add_argument("--json", action="store_true", help="print one JSON object")
    _feed_args(t)


def run(args: argparse.Namespace) -> int:
    """Run the `mcap` tool named in args.tool; returns the exit code."""
    if args.tool == "inspect":
        return run_inspect(args)
    if args.tool == "play":
        from .play import run_play

        return run_play(args)
    if args.tool == "live":
        from .live import run_live

        return run_live(args)
    if args.tool == "feed":
        from .feed import run_feed

        return run_feed(args)
    if args.tool == "export":
        from .export import run_export

        return run_export(args)
    from .rescore_cli import run_rescore

    return run_rescore(args)


def inspect_failed(episode: dict, verify: bool) -> bool:
    """Whether one file's summary makes `inspect` exit 1: damage or invalid transitions, and with --verify
    also a file that ends early (cut, or its writer did not finish it)."""
    return (episode["health"] == "damaged" or bool(episode["invalid_transitions"])
            or (verify and episode["health"] != "complete"))


def run_inspect(args: argparse.Namespace) -> int:
    """`romannet mcap inspect`; every file is reported, then exit code 1 if one was skipped (not an
    episode) or failed (see inspect_failed), each named in one line on stderr."""
    from romannet.common.episode_file import EpisodeFileError, episode_paths

    from .summary import format_episode, format_totals, summarize, to_json

    episodes, errors = [], []
    for path in episode_paths(args.inputs):
        try:
            episode = summarize(path, verify=args.verify)
        except EpisodeFileError as err:
            errors.append(str(err))
            sys.stderr.write(f"romannet mcap inspect: error: {err}\n")
            continue
        episodes.append(episode)
        if inspect_failed(episode, args.verify) and episode["health"] != "complete":
            sys.stderr.write(f"romannet mcap inspect: error: {path}: {episode['health_detail']}\n")
    if args.json:
        sys.stdout.write(to_json(episodes, errors) + "\n")
    else:
        for e in episodes:
            sys.stdout.write(format_episode(e) + "\n")
        if len(episodes) > 1:
            from .summary import totals

            sys.stdout.write("total: " + format_totals(totals(episodes)) + "\n")
    return 1 if errors or any(inspect_failed(e, args.verify) for e in episodes) else 0
