"""Writing an episode file from recorded messages (what `romannet mcap rescore` writes).

The new file has the layout the actor writes (docs/recording.md): metadata first, the same schemas and
channels (registered when their first message comes, as the actor does), messages in the same order with
their recorded times, one chunk flushed per step, "episode_end" last. It is written to `<name>.tmp` and
renamed when finished, so a crash never leaves a half file under the final name.
"""

from __future__ import annotations

import os
from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from romannet.common.episode_file import STEP_TOPIC, ChannelInfo, RecordedMessage
from romannet.common.fsutil import fsync_directory


class EpisodeWriter:
    """`with EpisodeWriter(path, metadata) as w: w.write(channel, msg, data)`; finished on a clean exit,
    removed on an exception."""

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]], library: str = "romannet mcap",
                 chunk_bytes: int = 1 << 20):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._file = open(self._tmp, "wb")  # noqa: SIM115 - closed in __exit__
        # With the data-section CRC, as the actor writes: a changed metadata value is then found.
        self._writer = McapWriter(self._file, chunk_size=chunk_bytes, compression=CompressionType.ZSTD,
                                  enable_data_crcs=True)
        self._writer.start(profile="", library=library)
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        for name, values in metadata.items():
            self._writer.add_metadata(name, dict(values))

    def __enter__(self) -> EpisodeWriter:
        return self

    def _channel(self, channel: ChannelInfo) -> int:
        if channel.topic not in self._channels:
            key = (channel.schema_name, channel.schema_encoding, channel.schema_data)
            if key not in self._schemas:
                self._schemas[key] = self._writer.register_schema(*key)
            self._channels[channel.topic] = self._writer.register_channel(
                channel.topic, channel.message_encoding, self._schemas[key], dict(channel.metadata))
        return self._channels[channel.topic]

    def write(self, channel: ChannelInfo, msg: RecordedMessage, data: bytes | None = None) -> None:
        """msg with its recorded times and sequence; `data` replaces its bytes if given."""
        self._writer.add_message(self._channel(channel), log_time=msg.log_time_ns,
                                 data=msg.data if data is None else data, publish_time=msg.publish_time_ns,
                                 sequence=msg.sequence)
        if channel.topic == STEP_TOPIC:
            self._writer.flush()  # one chunk per step, as the actor writes

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        self._writer.add_metadata(name, dict(values))

    def __exit__(self, exc_type: object, *_: object) -> None:
        try:
            if exc_type is None:
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
        finally:
            self._file.close()
        if exc_type is None:
            os.replace(self._tmp, self.path)
            fsync_directory(self.path.parent)
        else:
            self._tmp.unlink(missing_ok=True)
