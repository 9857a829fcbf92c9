"""The replay server's insert check decodes every PNG in full: crafted PNGs behind valid CRCs are refused
with the "bad_image" token, which actors set aside instead of resending (replay/validate.py).

The server process itself refusing them is tested in test_replay_server.py."""

from __future__ import annotations

import pytest
from _wire_samples import CRAFTED_PNGS, pb_transition

from romannet.common import wire
from romannet.common.errors import DecodeError
from romannet.common.imagecodec import check_png_chunks, check_png_pixels, read_png_header
from romannet.common.replay_client import refused_for_good
from romannet.replay.rejections import classify_decode_error
from romannet.replay.validate import check_transition

FIELDS = ("color_before_png", "depth_before_png", "color_after_png", "depth_after_png")


def _crafted(field: str, craft: str) -> bytes:
    m = pb_transition()
    setattr(m, field, CRAFTED_PNGS[craft](getattr(m, field)))
    return m.SerializeToString()


@pytest.mark.parametrize("craft", sorted(CRAFTED_PNGS))
def test_crafted_pngs_pass_header_and_crc_checks_but_do_not_decode(craft: str) -> None:
    png = pb_transition().color_before_png
    bad = CRAFTED_PNGS[craft](png)
    assert read_png_header(bad) == read_png_header(png)
    check_png_chunks(bad)  # every CRC valid: only a full decode tells
    with pytest.raises(DecodeError, match="^color PNG is corrupt"):
        check_png_pixels(bad, 8, 2, "color")


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("craft", sorted(CRAFTED_PNGS))
def test_insert_check_refuses_a_crafted_png_as_bad_image(craft: str, field: str) -> None:
    data = _crafted(field, craft)
    # Without the decode the transition passes: the refusal below is the full decode's.
    assert check_transition(data, (8, 8), decode_pixels=False).step == 7
    with pytest.raises(DecodeError) as err:
        check_transition(data, (8, 8))
    message = str(err.value)
    assert message.startswith(f"invalid Transition: {field} PNG is corrupt"), message
    assert "\n" not in message
    reason = classify_decode_error(message)
    assert reason == "bad_image" and refused_for_good(reason)


def test_insert_check_accepts_a_valid_transition_with_its_fields() -> None:
    data = pb_transition().SerializeToString()
    msg = check_transition(data, (8, 8))
    full = wire.decode_transition(data, (8, 8))
    assert (msg.actor_id, msg.episode_id, msg.step, msg.action) == (full.actor_id, full.episode_id, full.step,
                                                                     full.action)
    assert msg.color_before.shape == (8, 8, 3) and msg.depth_before.shape == (8, 8)
