"""Independent check of duv logs with the `mcap` package from PyPI.

Usage: check_mcap.py FILE...  Prints one JSON object: per file, the message count per topic,
the schema name per topic, whether the summary (index) was readable, and the time span.
"""
import json
import sys

from mcap.reader import make_reader

out = {}
for path in sys.argv[1:]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        counts, schemas = {}, {}
        first, last = None, None
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            schemas[channel.topic] = schema.name if schema is not None else ""
            first = message.log_time if first is None else min(first, message.log_time)
            last = message.log_time if last is None else max(last, message.log_time)
        metadata = [m.name for m in reader.iter_metadata()]
        out[path] = {
            "counts": counts,
            "schemas": schemas,
            "indexed": summary is not None and summary.statistics is not None,
            "statistics_messages": summary.statistics.message_count if summary and summary.statistics else None,
            "first": first,
            "last": last,
            "metadata": metadata,
        }
print(json.dumps(out))
