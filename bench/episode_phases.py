"""The command line the run analyses share (repeated_failures, pick_offsets): a run's recorded episodes,
split into training phases by episode number, one result per phase, printed as JSON or a line each."""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

import tomllib

from romannet.common.episode_file import TRANSITION_TOPIC, EpisodeFileError, episode_paths, read_episode
from romannet.common.errors import DecodeError
from romannet.common.wire import TransitionMsg, decode_transition


def episode_index(path: Path) -> int:
    """The number in an episode file's name (ep000012.mcap -> 12); -1 for a name without one."""
    digits = re.search(r"(\d+)$", path.stem)
    return int(digits.group(1)) if digits else -1


def recorded_transitions(path: Path) -> tuple[str, list[TransitionMsg]]:
    """An episode file's recorded config (TOML text) and its `/transition` records, decoded and validated.

    Each record is the wire message the actor sent: the action and the heightmaps before and after it, so
    nothing depends on how the other topics interleave. EpisodeFileError for an unreadable file or record.
    """
    episode = read_episode(path, topics=[TRANSITION_TOPIC])
    out = []
    for message in episode.of(TRANSITION_TOPIC):
        try:
            out.append(decode_transition(message.data))
        except DecodeError as err:
            raise EpisodeFileError(path, f"a /transition record does not decode: {err}") from err
    return episode.config_toml, out


def recorded_number(path: Path, config_toml: str, section: str, key: str) -> float:
    """A positive number from the config the actor recorded in an episode file (e.g. workspace.resolution_m);
    EpisodeFileError when it is missing or not a positive number."""
    try:
        value = tomllib.loads(config_toml)[section][key]
    except (tomllib.TOMLDecodeError, KeyError, TypeError) as err:
        raise EpisodeFileError(path, f"no {section}.{key} in its recorded config ({err})") from err
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and value > 0):
        raise EpisodeFileError(path, f"recorded {section}.{key} = {value!r} is not a positive number")
    return float(value)


def split_phases(files: list[Path], split: int) -> dict[str, list[Path]]:
    """{phase name: files}: one phase "all" if split <= 0, else episodes before `split` and from it on."""
    if split <= 0:
        return {"all": files}
    return {f"episodes < {split}": [f for f in files if episode_index(f) < split],
            f"episodes >= {split}": [f for f in files if episode_index(f) >= split]}


def phase_parser(description: str) -> argparse.ArgumentParser:
    """run_dir, --split and --json; the caller adds its own options."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("run_dir", help="a run directory (its episodes/) or a directory of episode files")
    p.add_argument("--split", type=int, default=0, help="first episode index of the second phase (0: one phase)")
    p.add_argument("--json", action="store_true")
    return p


def run_phases(args: argparse.Namespace, per_phase: Callable[[list[Path]], dict]) -> int:
    """per_phase(files) of each phase of args.run_dir, printed; exit status 2 (and the file's error on stderr)
    when a file is not a readable episode."""
    root = Path(args.run_dir)
    try:
        files = episode_paths([root / "episodes" if (root / "episodes").is_dir() else root])
        out = {name: per_phase(group) for name, group in split_phases(files, args.split).items()}
    except EpisodeFileError as err:
        print(err, file=sys.stderr)
        return 2
    print(json.dumps(out, indent=2) if args.json else "\n".join(f"{k}: {v}" for k, v in out.items()))
    return 0
