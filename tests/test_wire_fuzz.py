"""Fuzzing every decoder: random bytes and mutated valid messages raise DecodeError or decode, nothing else.

Mutations start from valid messages with 8x8 heightmaps, so many examples get past the protobuf framing
and reach the field checks and PNG decoding.
"""

from __future__ import annotations

import random
from collections.abc import Callable

import numpy as np
import pytest
from _wire_samples import all_messages
from hypothesis import given, settings
from hypothesis import strategies as st

from romannet.common import imagecodec
from romannet.common.errors import DecodeError

MESSAGES = all_messages(8, 8)
SEEDS: dict[str, bytes] = {name: encode(msg) for name, (msg, encode, _) in MESSAGES.items()}
SEEDS["color_png"] = imagecodec.encode_color_png(np.random.default_rng(0).integers(0, 256, (8, 8, 3), np.uint8))
SEEDS["depth_png"] = imagecodec.encode_depth_png(np.random.default_rng(1).uniform(0, 0.6, (8, 8)).astype(np.float32))
SEEDS["safetensors"] = MESSAGES["weights"][0].safetensors

DECODERS: dict[str, Callable[[bytes], object]] = {name: decode for name, (_, _, decode) in MESSAGES.items()}
DECODERS["color_png"] = imagecodec.decode_color_png
DECODERS["depth_png"] = imagecodec.decode_depth_png


def _decode_state_dict(data: bytes) -> object:
    weightscodec = pytest.importorskip("romannet.common.weightscodec")
    return weightscodec.decode_state_dict(data)


DECODERS["safetensors"] = _decode_state_dict


def mutate(seed: bytes, rng: random.Random) -> bytes:
    """seed with 1..4 random edits: bit flips, truncation, insertion, overwrite, duplication."""
    data = bytearray(seed)
    for _ in range(rng.randint(1, 4)):
        kind = rng.choice(["flip", "flip", "truncate", "insert", "overwrite", "duplicate"])
        pos = rng.randrange(len(data)) if data else 0
        if kind == "flip" and data:
            data[pos] ^= 1 << rng.randrange(8)
        elif kind == "truncate":
            del data[pos:]
        elif kind in ("insert", "overwrite"):
            chunk = rng.randbytes(rng.randint(1, 16))
            data[pos:pos + (len(chunk) if kind == "overwrite" else 0)] = chunk
        elif kind == "duplicate":
            end = rng.randint(pos, len(data))
            data[end:end] = data[pos:end]
    return bytes(data)


def fuzz_input(name: str) -> st.SearchStrategy[bytes]:
    # Mutations come from one drawn integer (a random.Random seed) rather than many draws: hypothesis spends
    # ~0.4 ms per draw-heavy example, which would dominate the suite's time; failures still replay exactly.
    return st.one_of(st.binary(max_size=512),
                     st.integers(0, 2**64 - 1).map(lambda s: mutate(SEEDS[name], random.Random(s))))


@pytest.mark.parametrize("name", sorted(DECODERS))
def test_seeds_decode(name: str) -> None:
    DECODERS[name](SEEDS[name])


@pytest.mark.timeout(120)
@pytest.mark.parametrize("name", sorted(DECODERS))
def test_decoder_raises_only_decode_error(name: str) -> None:
    decode = DECODERS[name]

    @settings(max_examples=2000)
    @given(fuzz_input(name))
    def check(data: bytes) -> None:
        try:
            decode(data)
        except DecodeError as exc:
            assert str(exc), "a DecodeError must say what is wrong"

    check()
