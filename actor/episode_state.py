"""An actor's actors/<id>/state.json: the next episode index, persisted before each episode starts.

Kept apart from the actor's service (no torch) so that `romannet up --resume` can check every actor's
state before it starts any process.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

from romannet.common.errors import RomannetError

__all__ = ["EpisodeStateError", "next_episode_index", "read_next_episode"]


class EpisodeStateError(RomannetError):
    """An actor's state.json exists but cannot be read: its next episode id is unknown."""


_EPISODE_FILE = re.compile(r"ep(\d{6,})\.mcap")


def read_next_episode(path: Path, episodes: Path | None = None) -> int:
    """The next episode index in state.json (0 when there is none yet: a new actor).

    A state.json that exists but is damaged is an EpisodeStateError naming the file, never a silent 0:
    an index already used would give new transitions the replay keys of old ones, and the server would
    drop them as duplicates. episodes (the actor's MCAP directory) only adds a suggested value to the error.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return 0
    except (OSError, UnicodeDecodeError) as err:
        problem = f"cannot be read ({getattr(err, 'strerror', None) or err})"
    else:
        problem = _episode_state_problem(text)
        if problem is None:
            return int(json.loads(text)["next_episode"])
    used = [int(m.group(1)) for f in (episodes.iterdir() if episodes and episodes.is_dir() else ())
            if (m := _EPISODE_FILE.fullmatch(f.name))]
    hint = f' (its recordings go up to ep{max(used):06d}: {{"next_episode": {max(used) + 1}}})' if used else ""
    raise EpisodeStateError(f"{path}: {problem}; the actor's next episode id is unknown and an id used before "
                            f"would make the replay server drop new transitions as duplicates. Write "
                            f'{{"next_episode": N}} there, N above every episode this actor has run{hint}')


def _episode_state_problem(text: str) -> str | None:
    """What is wrong with state.json's text, or None."""
    try:
        data = json.loads(text)
    except ValueError as err:
        return f"not valid JSON ({err})"
    index = data.get("next_episode") if isinstance(data, dict) else None
    if isinstance(index, bool) or not isinstance(index, int) or index < 0:
        return f'"next_episode" must be a whole number >= 0, got {index!r}'
    return None


def next_episode_index(path: Path, episodes: Path | None = None) -> int:
    """Take the next episode index from state.json and persist index + 1 before the episode starts."""
    index = read_next_episode(path, episodes)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump({"next_episode": index + 1}, f)
        f.flush()
        os.fsync(f.fileno())  # a crash must not hand out the same episode id twice
    os.replace(tmp, path)
    return index
