"""Read geocal exports with Apache Spark, DuckDB, polars and pyarrow (tests/export_parquet.rs).

Reads on stdin, as JSON:
  {"fleets": {name: folder},
   "spark_setup": python code (docs/fleet.md's Spark setup block, paths under `fleet/`),
   "spark_queries": {name: sql}, "duckdb_setup": [sql with `fleet/`], "duckdb_queries": {...},
   "tables": [table names]}
For every fleet: runs the Spark setup and every Spark query in ONE local[2] SparkSession (one
JVM for every fleet), the DuckDB setup and queries, and per table a summary each engine makes
itself (rows per machine key, name, serial and run; the types of the machine columns). Prints
{fleet: {"spark": {query: rows}, "duckdb": {query: rows},
         "summary": {engine: {table: rows}}, "types": {engine: {table: {column: type}}}}}
as JSON (dates and timestamps as ISO strings).
"""
import json
import sys
import time

SUMMARY_COLUMNS = ["machine_key", "machine", "machine_serial", "run_id"]


def plain(value):
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return value


def rows_of(rows):
    return [[plain(v) for v in row] for row in rows]


def summary_sql(source):
    keys = ", ".join(SUMMARY_COLUMNS)
    return f"SELECT {keys}, count(*) AS n FROM {source} GROUP BY {keys} ORDER BY {keys}"


def spark_part(spark, fleets, request, out):
    for fleet, folder in fleets.items():
        setup = request["spark_setup"].replace('"fleet/', f'"{folder}/').replace(
            "'fleet/", f"'{folder}/"
        )
        exec(setup, {"spark": spark})  # the docs' setup block, as written there
        answers = {}
        for name, sql in request["spark_queries"].items():
            try:
                answers[name] = rows_of(spark.sql(sql).collect())
            except Exception as e:  # name the query that failed
                sys.exit(f"Spark query {name} on {fleet} failed: {e}\n{sql}")
        out[fleet]["spark"] = answers
        summary, types = {}, {}
        for table in request["tables"]:
            summary[table] = rows_of(spark.sql(summary_sql(table)).collect())
            dtypes = dict(spark.table(table).dtypes)
            types[table] = {c: dtypes.get(c) for c in SUMMARY_COLUMNS}
        out[fleet]["summary"]["spark"] = summary
        out[fleet]["types"]["spark"] = types


def duckdb_part(fleets, request, out):
    import duckdb

    for fleet, folder in fleets.items():
        con = duckdb.connect()
        for sql in request["duckdb_setup"]:
            con.execute(sql.replace("'fleet/", f"'{folder}/"))
        answers = {}
        for name, sql in request["duckdb_queries"].items():
            try:
                answers[name] = rows_of(con.execute(sql).fetchall())
            except Exception as e:
                sys.exit(f"DuckDB query {name} on {fleet} failed: {e}\n{sql}")
        out[fleet]["duckdb"] = answers
        summary, types = {}, {}
        for table in request["tables"]:
            summary[table] = rows_of(con.execute(summary_sql(table)).fetchall())
            described = {r[0]: r[1] for r in con.execute(f"DESCRIBE {table}").fetchall()}
            types[table] = {c: described.get(c) for c in SUMMARY_COLUMNS}
        out[fleet]["summary"]["duckdb"] = summary
        out[fleet]["types"]["duckdb"] = types


def polars_part(fleets, request, out):
    import polars as pl

    for fleet, folder in fleets.items():
        summary, types = {}, {}
        for table in request["tables"]:
            frame = pl.read_parquet(f"{folder}/{table}")
            grouped = (
                frame.group_by(SUMMARY_COLUMNS)
                .agg(pl.len().alias("n"))
                .sort(SUMMARY_COLUMNS, nulls_last=False)
            )
            summary[table] = rows_of(grouped.rows())
            types[table] = {c: str(frame.schema.get(c)) for c in SUMMARY_COLUMNS}
        out[fleet]["summary"]["polars"] = summary
        out[fleet]["types"]["polars"] = types


def pyarrow_part(fleets, request, out):
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    for fleet, folder in fleets.items():
        summary, types = {}, {}
        for table in request["tables"]:
            data = pq.read_table(f"{folder}/{table}")  # as pandas.read_parquet reads it
            columns = {}
            for c in SUMMARY_COLUMNS:
                column = data.column(c)
                if str(column.type).startswith("dictionary"):
                    column = pc.cast(column, "string")
                columns[c] = column.to_pylist()
            counts = {}
            for row in zip(*(columns[c] for c in SUMMARY_COLUMNS)):
                counts[row] = counts.get(row, 0) + 1
            summary[table] = sorted(
                ([*row, n] for row, n in counts.items()),
                key=lambda r: [(v is not None, v or "") for v in r[:-1]],
            )
            types[table] = {c: str(data.schema.field(c).type) for c in SUMMARY_COLUMNS}
        out[fleet]["summary"]["pyarrow"] = summary
        out[fleet]["types"]["pyarrow"] = types


def main():
    request = json.load(sys.stdin)
    fleets = request["fleets"]
    out = {f: {"summary": {}, "types": {}} for f in fleets}
    timings = {}
    start = time.monotonic()
    duckdb_part(fleets, request, out)
    polars_part(fleets, request, out)
    pyarrow_part(fleets, request, out)
    timings["duckdb_polars_pyarrow_s"] = time.monotonic() - start

    from pyspark.sql import SparkSession

    start = time.monotonic()
    spark = (
        SparkSession.builder.master("local[2]")
        .appName("geocal-export-test")
        .config("spark.ui.enabled", "false")
        .config("spark.sql.shuffle.partitions", "2")
        .config("spark.sql.session.timeZone", "UTC")
        .getOrCreate()
    )
    spark.sparkContext.setLogLevel("ERROR")
    timings["spark_start_s"] = time.monotonic() - start
    try:
        spark_part(spark, fleets, request, out)
    finally:
        spark.stop()
    timings["spark_total_s"] = time.monotonic() - start
    json.dump({"fleets": out, "timings": timings}, sys.stdout, default=str)


if __name__ == "__main__":
    main()
