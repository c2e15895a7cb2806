"""Repair an episode file that a crash left unfinished (``….mcap.part``).

    python -m l2r.episodes.recover runs/exp1/episodes/exp1-a0-…-train.mcap.part [-o OUT]

Keeps every schema, channel, metadata record and message up to the last whole record and
writes them into a new, complete MCAP file (zstd chunks, summary, indexes), by default next
to the input as ``….recovered.mcap``. It does what ``mcap recover`` of the mcap CLI does,
for hosts without that tool.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from l2r.episodes.read import iter_records


def recover(source: str | Path, target: str | Path) -> dict[str, int]:
    """Copy what is readable of ``source`` into a complete file ``target``; counts of what was kept."""
    counts = {"messages": 0, "metadata": 0, "channels": 0, "attachments": 0}
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    with open(target, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="l2r", library="l2r recover")
        for record in iter_records(source):
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), dict(record.metadata)
                )
                counts["channels"] += 1
            elif isinstance(record, Message) and record.channel_id in channel_ids:
                writer.add_message(channel_ids[record.channel_id], record.log_time, record.data,
                                   record.publish_time, record.sequence)  # fmt: skip
                counts["messages"] += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
                counts["metadata"] += 1
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
                counts["attachments"] += 1
        writer.finish()
    return counts


def default_target(source: Path) -> Path:
    name = source.name.removesuffix(".part").removesuffix(".mcap")
    return source.with_name(name + ".recovered.mcap")


def cli(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m l2r.episodes.recover", description="Repair episode files a crash left unfinished (.mcap.part) into complete .mcap files.")
    parser.add_argument("files", nargs="+", type=Path, help="interrupted episode files (.mcap.part or .mcap)")
    parser.add_argument("-o", "--output", type=Path, help="output file (only with one input)")
    args = parser.parse_args(argv)
    if args.output and len(args.files) > 1:
        parser.error("--output takes one input file")
    status = 0
    for source in args.files:
        if not source.is_file():
            print(f"{source}: no such file", file=sys.stderr)
            status = 1
            continue
        target = args.output or default_target(source)
        counts = recover(source, target)
        print(f"{source} -> {target}: {counts['messages']} messages, {counts['metadata']} metadata records")
        if not counts["messages"]:
            print(f"{source}: nothing readable (no whole chunk was written before the crash)", file=sys.stderr)
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(cli())
