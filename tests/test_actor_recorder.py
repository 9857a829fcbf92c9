"""MCAP episode recorder: a recorded episode reads back with mcap's readers (seeking, with the summary, and
non-seeking on a truncated copy / a never-finished file) with the right step count and decodable images."""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from _replay_helpers import tr
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import NonSeekingReader, make_reader

from romannet.actor.recorder import TRANSITION_TOPIC, EpisodeRecorder, colorize, count_steps, step_record
from romannet.common.interfaces import Observation
from romannet.common.wire import decode_transition, encode_transition

pytestmark = pytest.mark.timeout(60)
H = W = 16


def _obs(seed: int, camera: bool = True) -> Observation:
    rng = np.random.default_rng(seed)
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.uniform(0.0, 0.3, (H, W)).astype(np.float32)
    cam_color = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) if camera else None
    cam_depth = rng.uniform(0.5, 0.8, (24, 32)).astype(np.float32) if camera else None
    return Observation(color, depth, False, cam_color, cam_depth)


def _record(path: Path, steps: int, finish: bool = True, **kw) -> EpisodeRecorder:
    rec = EpisodeRecorder(path, {"run_id": "r1", "actor_id": "a0", "task": "clutter", "seed": 7,
                                 "weights_version_start": 3}, config_toml="run_id = \"r1\"\n",
                          chunk_bytes=64 * 1024, **kw)
    rec.write_observation(_obs(0), 1_000)
    for step in range(steps):
        q = {"push": np.linspace(0, 1, H * W, dtype=np.float32).reshape(H, W),
             "pick": np.full((H, W), 0.5, np.float32)}
        ranges = rec.write_q_maps(q, 2_000 + step)
        data = encode_transition(tr(step, episode="ep000000", actor="a0", size=H))
        rec.write_observation(_obs(step + 1), 3_000 + step)  # the observation after, then the step (flushes)
        rec.write_step(data, {"step": step, "q_ranges": ranges, "reward": np.float32(0.5)}, 3_000 + step)
    if finish:
        rec.close({"done_reason": "done", "steps": steps})
    return rec


def _by_topic(messages) -> dict[str, list]:
    out: dict[str, list] = {}
    for schema, channel, message in messages:
        out.setdefault(channel.topic, []).append((schema, message))
    return out


def test_episode_reads_back_with_summary(tmp_path: Path) -> None:
    path = tmp_path / "ep000000.mcap"
    _record(path, steps=3)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
        assert counts[TRANSITION_TOPIC] == 3 and counts["/step"] == 3
        assert counts["/heightmap/color"] == counts["/heightmap/depth"] == 4  # N + 1 observations
        assert counts["/camera/color"] == counts["/camera/depth"] == 4
        assert counts["/q/push"] == counts["/q/pick"] == 3
        schemas = {summary.channels[cid].topic: summary.schemas[summary.channels[cid].schema_id].name
                   for cid in summary.channels}
        assert schemas["/camera/color"] == "foxglove.CompressedImage"
        assert schemas["/heightmap/depth"] == "foxglove.RawImage"
        assert schemas[TRANSITION_TOPIC] == "romannet.v1.Transition"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["romannet"]["actor_id"] == "a0" and meta["romannet"]["weights_version_start"] == "3"
        assert meta["config"]["toml"].startswith("run_id")
        assert meta["episode_end"]["done_reason"] == "done"
        topics = _by_topic(reader.iter_messages())
    steps = [decode_transition(m.data) for _, m in topics[TRANSITION_TOPIC]]
    assert [t.step for t in steps] == [0, 1, 2] and steps[0].shape == (H, W)
    assert json.loads(topics["/step"][0][1].data)["reward"] == pytest.approx(0.5)
    img = CompressedImage.FromString(topics["/heightmap/color"][0][1].data)
    color = cv2.cvtColor(cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(color, _obs(0).color_hm)  # PNG: lossless
    raw = RawImage.FromString(topics["/heightmap/depth"][1][1].data)
    assert (raw.encoding, raw.width, raw.height, raw.step) == ("16UC1", W, H, 2 * W)
    depth = np.frombuffer(raw.data, "<u2").reshape(H, W) * 1e-5
    np.testing.assert_allclose(depth, _obs(1).depth_hm, atol=1e-5)
    cam = CompressedImage.FromString(topics["/camera/color"][0][1].data)
    assert cam.format == "jpeg" and cv2.imdecode(np.frombuffer(cam.data, np.uint8), cv2.IMREAD_COLOR).shape == (24, 32, 3)
    cam_depth = RawImage.FromString(topics["/camera/depth"][0][1].data)
    mm = np.frombuffer(cam_depth.data, "<u2").reshape(24, 32)
    np.testing.assert_allclose(mm / 1000.0, _obs(0).camera_depth_m, atol=1e-3)
    q = CompressedImage.FromString(topics["/q/push"][0][1].data)
    assert cv2.imdecode(np.frombuffer(q.data, np.uint8), cv2.IMREAD_COLOR).shape == (H, W, 3)
    assert count_steps(path) == 3


def test_truncated_copy_reads_with_a_non_seeking_reader(tmp_path: Path) -> None:
    path = tmp_path / "ep000000.mcap"
    _record(path, steps=4)
    data = path.read_bytes()
    # Cut inside the last step's chunk: the summary and footer are gone, earlier chunks are whole.
    cut = data[: int(len(data) * 0.8)]
    (tmp_path / "cut.mcap").write_bytes(cut)
    transitions = []
    reader = NonSeekingReader(io.BytesIO(cut))
    with pytest.raises(Exception):  # noqa: B017 - whatever the reader raises at the damaged end is fine
        for _, channel, message in reader.iter_messages(log_time_order=False):
            if channel.topic == TRANSITION_TOPIC:
                transitions.append(decode_transition(message.data))
    assert 1 <= len(transitions) <= 4
    assert [t.step for t in transitions] == list(range(len(transitions)))
    assert count_steps(tmp_path / "cut.mcap") == len(transitions)


def test_unfinished_file_keeps_every_flushed_step(tmp_path: Path) -> None:
    """A crash before close(): each step was flushed as its own chunk, so all of them read back."""
    path = tmp_path / "ep000000.mcap"
    rec = _record(path, steps=3, finish=False)
    try:
        assert count_steps(path) == 3
        with open(path, "rb") as f:
            reader = NonSeekingReader(f)
            images = 0
            try:
                for _, channel, message in reader.iter_messages(log_time_order=False):
                    if channel.topic == "/heightmap/color":
                        CompressedImage.FromString(message.data)
                        images += 1
            except Exception:  # the file simply ends (no summary, no footer)
                pass
        assert images == 4
    finally:
        rec.close()
    assert count_steps(path) == 3


def test_png_camera_and_no_camera(tmp_path: Path) -> None:
    _record(tmp_path / "png.mcap", steps=1, camera_color_format="png")
    _record(tmp_path / "nocam.mcap", steps=1, record_camera=False, compression="none")
    with open(tmp_path / "png.mcap", "rb") as f:
        topics = _by_topic(make_reader(f).iter_messages())
    assert CompressedImage.FromString(topics["/camera/color"][0][1].data).format == "png"
    with open(tmp_path / "nocam.mcap", "rb") as f:
        topics = _by_topic(make_reader(f).iter_messages())
    assert "/camera/color" not in topics and len(topics[TRANSITION_TOPIC]) == 1


def test_colorize_handles_flat_and_nonfinite_maps() -> None:
    img, lo, hi = colorize(np.array([[0.0, 1.0], [np.nan, 0.5]], np.float32))
    assert img.shape == (2, 2, 3) and img.dtype == np.uint8 and (lo, hi) == (0.0, 1.0)
    img, lo, hi = colorize(np.full((3, 3), 2.0, np.float32))
    assert (lo, hi) == (2.0, 2.0) and len({tuple(p) for p in img.reshape(-1, 3)}) == 1


def test_the_step_record_repeats_its_transition_and_adds_what_a_transition_lacks(tmp_path: Path) -> None:
    msg = tr(4, episode="ep000003", actor="a0", size=H)
    record = step_record(msg, [0.5, -0.1, 0.02], "nothing_grasped", {"pick": (0.0, 1.0)}, {"seed": 9})
    a = msg.action
    assert (record["step"], record["episode_id"], record["primitive"], record["row"], record["col"]) == \
        (4, "ep000003", a.primitive, a.row, a.col)
    for name in ("success", "progress_before", "progress_after", "reward", "done", "done_reason",
                 "holding_before", "holding_after", "explore_rate"):
        assert record[name] == getattr(msg, name), name
    assert record["weights_version"] == msg.policy_version and record["q_value"] == a.q_value
    assert (record["position_m"], record["detail"], record["q_ranges"], record["info"]) == \
        ([0.5, -0.1, 0.02], "nothing_grasped", {"pick": (0.0, 1.0)}, {"seed": 9})
    # Written and read back as the JSON of the /step channel.
    rec = EpisodeRecorder(tmp_path / "ep.mcap", {"run_id": "r1", "actor_id": "a0"}, record_camera=False)
    rec.write_step(encode_transition(msg), record, 5_000)
    rec.close()
    with open(tmp_path / "ep.mcap", "rb") as f:
        steps = [json.loads(m.data) for _, c, m in make_reader(f).iter_messages() if c.topic == "/step"]
    assert steps == [{**record, "q_ranges": {"pick": [0.0, 1.0]}}]
