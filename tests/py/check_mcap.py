"""Independent check of duv logs with the `mcap` package from PyPI.

Usage: check_mcap.py FILE...  Prints one JSON object: per file, the message count per topic,
the schema name per topic, whether the summary (index) was readable, the time span, and per
topic the number of `foxglove.CompressedImage` messages whose format is "jpeg" and whose data
is a whole JPEG stream (SOI ... EOI), read with a protobuf walker of its own.
"""
import json
import sys

from mcap.reader import make_reader


def varint(buf, i):
    v, shift = 0, 0
    while True:
        b = buf[i]
        i += 1
        v |= (b & 0x7F) << shift
        if b < 0x80:
            return v, i
        shift += 7


def proto_fields(buf):
    """Top-level fields of a protobuf message: {field number: value} (bytes for LEN)."""
    out, i = {}, 0
    while i < len(buf):
        key, i = varint(buf, i)
        field, wire = key >> 3, key & 7
        if wire == 0:
            v, i = varint(buf, i)
        elif wire == 1:
            v, i = buf[i:i + 8], i + 8
        elif wire == 2:
            n, i = varint(buf, i)
            v, i = buf[i:i + n], i + n
        elif wire == 5:
            v, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wire}")
        out[field] = v
    return out


def is_jpeg_compressed_image(data):
    """foxglove.CompressedImage: data = 2, format = 3."""
    f = proto_fields(data)
    jpeg, fmt = f.get(2, b""), f.get(3, b"")
    return fmt == b"jpeg" and jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9"


out = {}
for path in sys.argv[1:]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        counts, schemas, jpeg = {}, {}, {}
        first, last = None, None
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            schemas[channel.topic] = schema.name if schema is not None else ""
            if schema is not None and schema.name == "foxglove.CompressedImage" and is_jpeg_compressed_image(message.data):
                jpeg[channel.topic] = jpeg.get(channel.topic, 0) + 1
            first = message.log_time if first is None else min(first, message.log_time)
            last = message.log_time if last is None else max(last, message.log_time)
        metadata = [m.name for m in reader.iter_metadata()]
        out[path] = {
            "counts": counts,
            "schemas": schemas,
            "jpeg": jpeg,
            "indexed": summary is not None and summary.statistics is not None,
            "statistics_messages": summary.statistics.message_count if summary and summary.statistics else None,
            "first": first,
            "last": last,
            "metadata": metadata,
        }
print(json.dumps(out))
