"""What the run diagnostics share: a run's recorded episodes, read back as the actor sent them and split
into training phases by episode number, one result per phase."""

from __future__ import annotations

import re
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


def by_phase(run_dir: Path, split: int, per_phase: Callable[[list[Path]], dict]) -> dict:
    """{phase name: per_phase(its files)} over run_dir/episodes (or run_dir itself: a directory of episode
    files, or one file); EpisodeFileError names a path that is missing or a file that is not an episode."""
    files = episode_paths([run_dir / "episodes" if (run_dir / "episodes").is_dir() else run_dir])
    return {name: per_phase(group) for name, group in split_phases(files, split).items()}
