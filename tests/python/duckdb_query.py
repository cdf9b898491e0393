"""Run SQL against a geocal export with DuckDB, an outside reader (tests/export_parquet.rs).

Reads {"setup": [sql, ...], "queries": {name: sql}} as JSON on stdin; runs the setup
statements, then each query, and prints {name: {"columns": [...], "rows": [[...], ...]}} as
JSON (dates and timestamps as ISO strings, lists as lists).
"""
import json
import sys

import duckdb


def main():
    request = json.load(sys.stdin)
    con = duckdb.connect()
    for sql in request.get("setup", []):
        con.execute(sql)
    out = {}
    for name, sql in request["queries"].items():
        try:
            cursor = con.execute(sql)
        except Exception as e:  # name the query that failed
            sys.exit(f"query {name} failed: {e}\n{sql}")
        columns = [d[0] for d in cursor.description]
        rows = [list(r) for r in cursor.fetchall()]
        out[name] = {"columns": columns, "rows": rows}
    json.dump(out, sys.stdout, default=str)


if __name__ == "__main__":
    main()
