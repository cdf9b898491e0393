"""Rewrites an MCAP session with the Python `mcap` writer, as an independent recorder lays it
out: another chunk size and compression, or no chunks at all. Every message, channel and
schema is copied unchanged (same log and publish times, same sequence numbers), so geocal's
results on the copy must equal its results on the original; only the file's layout differs.

Used by `cargo bench --bench solve_session` for its other-writer rows.

    python3 bench/rewrite_session.py SRC DST [--compression zstd|lz4|none]
                                     [--chunk-size BYTES] [--unchunked]
"""

import argparse
import os
import sys

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("src")
    parser.add_argument("dst")
    parser.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    parser.add_argument("--chunk-size", type=int, default=4 * 1024 * 1024)
    parser.add_argument("--unchunked", action="store_true")
    args = parser.parse_args()
    compression = {
        "zstd": CompressionType.ZSTD,
        "lz4": CompressionType.LZ4,
        "none": CompressionType.NONE,
    }[args.compression]
    partial = args.dst + ".partial"
    with open(args.src, "rb") as src, open(partial, "wb") as dst:
        reader = make_reader(src)
        header = reader.get_header()
        writer = Writer(
            dst,
            chunk_size=args.chunk_size,
            compression=compression,
            use_chunking=not args.unchunked,
        )
        writer.start(profile=header.profile, library="python mcap writer (geocal bench)")
        schema_ids = {}
        channel_ids = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data
                )
            if channel.id not in channel_ids:
                channel_ids[channel.id] = writer.register_channel(
                    topic=channel.topic,
                    message_encoding=channel.message_encoding,
                    schema_id=schema_ids.get(channel.schema_id, 0),
                    metadata=dict(channel.metadata),
                )
            writer.add_message(
                channel_id=channel_ids[channel.id],
                log_time=message.log_time,
                data=message.data,
                publish_time=message.publish_time,
                sequence=message.sequence,
            )
        writer.finish()
    os.replace(partial, args.dst)
    return 0


if __name__ == "__main__":
    sys.exit(main())
