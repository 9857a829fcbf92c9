"""One run's training curves (romannet.evaluate.run_curves) as TensorBoard events, with the run's resolved
config as text and its learning settings as hparams.

They go to RUN_DIR/tensorboard/episodes/ (`tensorboard --logdir runs` lists it beside the learner's
RUN_DIR/tensorboard), step = training actions (all actors):

    actions/success_rate  actions/efficiency  actions/per_second     every `stride` actions
    episodes/return  episodes/length  episodes/completion_rate       every finished episode
    config (text: config.toml)   hparams (the learning sections of the config; metrics: the tags above)

Written with tensorboard's own event writer (no torch: the launcher that writes it never imports torch).
A writer rewrites the whole history when it opens: it removes the directory's earlier event files and
starts with a SessionLog START at step 0, so a TensorBoard that already read an earlier launch's points
drops them instead of drawing them twice.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from tensorboard.compat.proto.event_pb2 import Event, SessionLog
from tensorboard.compat.proto.summary_pb2 import Summary, SummaryMetadata
from tensorboard.compat.proto.tensor_pb2 import TensorProto
from tensorboard.compat.proto.tensor_shape_pb2 import TensorShapeProto
from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2
from tensorboard.plugins.hparams import summary_v2 as hparams_summary
from tensorboard.plugins.text.plugin_data_pb2 import TextPluginData
from tensorboard.summary.writer.event_file_writer import EventFileWriter

from .run_curves import RunCurves

HPARAM_SECTIONS = ("task", "workspace", "model", "reward", "exploration", "replay", "learner")
ACTION_TAGS = ("actions/success_rate", "actions/efficiency", "actions/per_second")
EPISODE_TAGS = ("episodes/return", "episodes/length", "episodes/completion_rate")


def flat_hparams(config: Mapping[str, Any], sections: Iterable[str] = HPARAM_SECTIONS) -> dict[str, Any]:
    """`section.field` -> value for the given sections of a config dict (configbase.to_dict), plus `seed`;
    values TensorBoard cannot hold (lists, tables, None) as their text."""
    out: dict[str, Any] = {"seed": config.get("seed")} if "seed" in config else {}
    for section in sections:
        for name, value in (config.get(section) or {}).items():
            ok = isinstance(value, bool | int | float | str)
            out[f"{section}.{name}"] = value if ok else str(value)
    return out


def _hparam_type(value: Any) -> int:
    if isinstance(value, bool):
        return api_pb2.DATA_TYPE_BOOL
    return api_pb2.DATA_TYPE_FLOAT64 if isinstance(value, int | float) else api_pb2.DATA_TYPE_STRING


def experiment_summary(hparams: Mapping[str, Any], metric_tags: Iterable[str]) -> Summary:
    """The hparams plugin's experiment: which hparams and metrics its table has."""
    experiment = api_pb2.Experiment(
        hparam_infos=[api_pb2.HParamInfo(name=k, type=_hparam_type(v)) for k, v in hparams.items()],
        metric_infos=[api_pb2.MetricInfo(name=api_pb2.MetricName(tag=t)) for t in metric_tags])
    content = plugin_data_pb2.HParamsPluginData(version=metadata.PLUGIN_DATA_VERSION, experiment=experiment)
    return Summary(value=[Summary.Value(tag=metadata.EXPERIMENT_TAG,
                                        metadata=metadata.create_summary_metadata(content))])


def text_summary(tag: str, text: str) -> Summary:
    """A text-plugin summary (markdown), as torch.utils.tensorboard writes it."""
    meta = SummaryMetadata(plugin_data=SummaryMetadata.PluginData(
        plugin_name="text", content=TextPluginData(version=0).SerializeToString()))
    tensor = TensorProto(dtype="DT_STRING", string_val=[text.encode("utf-8")],
                         tensor_shape=TensorShapeProto(dim=[TensorShapeProto.Dim(size=1)]))
    return Summary(value=[Summary.Value(tag=tag, metadata=meta, tensor=tensor)])


def as_markdown_code(text: str) -> str:
    """Text shown verbatim by TensorBoard's markdown: every line indented four spaces."""
    return "\n".join("    " + line for line in text.splitlines())


class CurvesBoard:
    """The event file of one run's curves; `write` adds the points past those already written."""

    def __init__(self, log_dir: Path, config_toml: str, hparams: Mapping[str, Any], stride: int = 10):
        log_dir.mkdir(parents=True, exist_ok=True)
        for old in log_dir.glob("events.out.tfevents.*"):  # rewritten whole below
            old.unlink()
        self.log_dir, self.stride = log_dir, max(1, int(stride))
        self._writer = EventFileWriter(str(log_dir))
        self._last: dict[str, int] = {}
        self._event(0, session_log=SessionLog(status=SessionLog.START))
        self._event(0, summary=text_summary("config", as_markdown_code(config_toml)))
        self._event(0, summary=experiment_summary(hparams, (*ACTION_TAGS, *EPISODE_TAGS)))
        self._event(0, summary=hparams_summary.hparams_pb(dict(hparams)))

    def _event(self, step: int, **fields: Any) -> None:
        self._writer.add_event(Event(wall_time=time.time(), step=int(step), **fields))

    def _series(self, tag: str, xs: np.ndarray, ys: np.ndarray, stride: int) -> None:
        last = self._last.get(tag, 0)
        for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
            if x >= last + stride and np.isfinite(y):
                self._event(x, summary=Summary(value=[Summary.Value(tag=tag, simple_value=float(y))]))
                last = x
        self._last[tag] = last

    def write(self, curves: RunCurves) -> None:
        """Add every point past the last written one of each tag, and flush."""
        per_action = (curves.success_rate, curves.efficiency, curves.actions_per_s)
        for tag, ys in zip(ACTION_TAGS, per_action, strict=True):
            self._series(tag, curves.action_x, ys, self.stride)
        per_episode = (curves.episode_return, curves.episode_length, curves.completion_rate)
        for tag, ys in zip(EPISODE_TAGS, per_episode, strict=True):
            self._series(tag, curves.episode_x, ys, 1)
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()
