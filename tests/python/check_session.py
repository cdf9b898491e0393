#!/usr/bin/env python3
"""Independent check of a geocal session file (geocal-session/1) with the PyPI `mcap` reader.

Reads every message, checks it is JSON valid against its channel's JSON Schema, prints counts
per topic, and exits non-zero on any failure. Needs: pip install mcap jsonschema
"""
import argparse
import collections
import json
import re
import sys

try:
    from mcap.reader import make_reader
    import jsonschema
except ImportError as err:  # the Rust test turns this exit code into a clear failure
    print(f"missing Python module ({err}); run: pip install mcap jsonschema", file=sys.stderr)
    sys.exit(3)

SCHEMA_BY_TOPIC = [
    (re.compile(r"^/geocal/session$"), "geocal.Session"),
    (re.compile(r"^/run/event$"), "geocal.RunEvent"),
    (re.compile(r"^/tracer/[^/]+/range$"), "geocal.TracerSample"),
    (re.compile(r"^/env/[^/]+$"), "geocal.EnvSample"),
    (re.compile(r"^/rotary/[^/]+/state$"), "geocal.RotaryState"),
    (re.compile(r"^/machine/[^/]+/state$"), "geocal.MachineState"),
    (re.compile(r"^/probe/[^/]+/reading$"), "geocal.ProbeReading"),
]


def expected_schema(topic):
    for pattern, name in SCHEMA_BY_TOPIC:
        if pattern.match(topic):
            return name
    return None


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("file")
    parser.add_argument("--expect-tracer-samples", type=int, default=None)
    parser.add_argument("--dump", default=None,
                        help="write every message as topic, log_time, publish_time, hex data")
    args = parser.parse_args()

    failures = []
    counts = collections.Counter()
    validators = {}
    last_log_time = None
    dump = open(args.dump, "w", encoding="ascii") if args.dump else None
    with open(args.file, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            topic = channel.topic
            counts[topic] += 1
            if dump:
                dump.write(f"{topic}\t{message.log_time}\t{message.publish_time}\t"
                           f"{message.data.hex()}\n")
            where = f"{topic} @ log_time {message.log_time}"
            if channel.message_encoding != "json":
                failures.append(f"{where}: message encoding {channel.message_encoding!r}")
                continue
            if schema is None or schema.encoding != "jsonschema":
                failures.append(f"{where}: channel has no jsonschema schema")
                continue
            want = expected_schema(topic)
            if want is not None and schema.name != want:
                failures.append(f"{where}: schema name {schema.name!r}, expected {want!r}")
            if last_log_time is not None and message.log_time < last_log_time:
                failures.append(f"{where}: log_time goes backwards")
            last_log_time = message.log_time
            try:
                validator = validators.get(schema.id)
                if validator is None:
                    schema_json = json.loads(schema.data)
                    cls = jsonschema.validators.validator_for(schema_json)
                    cls.check_schema(schema_json)
                    validator = cls(schema_json)
                    validators[schema.id] = validator
                doc = json.loads(message.data)
            except Exception as err:  # noqa: BLE001 - any failure is reported, not raised
                failures.append(f"{where}: {err}")
                continue
            for error in validator.iter_errors(doc):
                failures.append(f"{where}: {error.message}")
            if topic == "/geocal/session" and doc.get("format") != "geocal-session/1":
                failures.append(f"{where}: format {doc.get('format')!r}")

    if dump:
        dump.close()
    for topic in sorted(counts):
        print(f"{topic}\t{counts[topic]}")
    if counts["/geocal/session"] != 1:
        failures.append(f"{counts['/geocal/session']} /geocal/session messages, expected 1")
    tracer_total = sum(n for t, n in counts.items() if t.startswith("/tracer/"))
    print(f"tracer samples\t{tracer_total}")
    if args.expect_tracer_samples is not None and tracer_total != args.expect_tracer_samples:
        failures.append(
            f"{tracer_total} tracer samples, expected {args.expect_tracer_samples}")
    for failure in failures[:50]:
        print(f"FAIL: {failure}", file=sys.stderr)
    if failures:
        print(f"{len(failures)} failures", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
