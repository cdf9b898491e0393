"""The Python package against the command line (bit for bit), the `mcap` package's own reading
of the same files, and the example notebook. Run by tests/python_package.rs with:

GEOCAL_BIN       the geocal command line built from the same tree
GEOCAL_REPO      the repository (config/, examples/python/)
GEOCAL_SESSIONS  the outside sessions (../shared/sessions)
GEOCAL_WHEEL     the wheel installed here
GEOCAL_BARE_PYTHON  a Python of a virtual environment without site packages holding the wheel
"""

import glob
import json
import os
import shutil
import subprocess
import threading
import zipfile

import numpy as np
import pytest

import geocal

BIN = os.environ["GEOCAL_BIN"]
REPO = os.environ["GEOCAL_REPO"]
SESSIONS = os.environ["GEOCAL_SESSIONS"]
DEMO = os.path.join(REPO, "config", "demo-multilateration.toml")
CONFIGS = sorted(glob.glob(os.path.join(REPO, "config", "*.toml")))


def session(name):
    return os.path.join(SESSIONS, name, "session.mcap")


# One outside session of every plan kind.
OUTSIDE = [
    "outside-clean-7",
    "outside-rotary-clean-2",
    "outside-sphere-clean-2",
    "outside-probe-clean-2",
    "outside-hexapod-clean-2",
]


def cli(*args, check=True):
    done = subprocess.run(
        [BIN, "--quiet", *args], capture_output=True, text=True, check=False
    )
    if check:
        assert done.returncode == 0, done.stderr
    return done


def cli_solve_file(path, out, *extra):
    cli("solve", path, "--out", str(out), *extra)
    with open(out, encoding="utf-8") as f:
        return f.read()


def cli_error(*args):
    done = cli(*args, check=False)
    assert done.returncode != 0
    assert done.stderr.startswith("error: "), done.stderr
    return done.stderr[len("error: ") :].rstrip("\n")


def assert_steady_progress(calls):
    """Several steps of one total fixed at the start, from 0, never back, ending at it."""
    assert len(calls) > 2, calls
    total = calls[0][1]
    assert total > 1 and all(t == total for _, t in calls), calls
    done = [d for d, _ in calls]
    assert done[0] == 0 and done[-1] == total, calls
    assert all(a <= b for a, b in zip(done, done[1:])), calls


# --- check ------------------------------------------------------------------------------


@pytest.mark.parametrize("config", CONFIGS, ids=os.path.basename)
def test_check_equals_the_command_line(config):
    checked = geocal.check(config)
    assert checked.to_json() + "\n" == cli("check", config, "--json").stdout
    assert cli("check", config).stdout == f"{config}: valid\n{checked.text}"
    assert checked.data == json.loads(checked.to_json())


# --- run ----------------------------------------------------------------------------------


@pytest.mark.parametrize("config", CONFIGS, ids=os.path.basename)
def test_run_every_kind_solves_as_the_command_line(config, tmp_path):
    calls = []
    out = geocal.run(config, tmp_path / "run", progress=lambda d, t: calls.append((d, t)))
    with open(out.results_path, encoding="utf-8") as f:
        written = f.read()
    assert out.results.to_json() == written
    # The live run's results are the replay's: the command line's solve of the same file.
    assert written == cli_solve_file(out.session_path, tmp_path / "cli.json")
    assert calls, "no progress reported"
    done, total = calls[-1]
    assert done == total > 0
    assert all(0 <= d <= t for d, t in calls)
    assert out.results.kind == json.loads(written)["kind"]
    assert out.results.parameters.num_rows > 0


def test_a_progress_callback_that_raises_stops_reporting_and_raises(tmp_path):
    calls = []

    def stop(done, total):
        calls.append(done)
        if done >= 3:
            raise RuntimeError("enough")

    with pytest.raises(RuntimeError, match="enough"):
        geocal.run(DEMO, tmp_path / "cut", progress=stop)
    # Called no more once it raised; the run was cancelled as Ctrl-C cancels `geocal run`:
    # its session is kept (to resume) and nothing was solved.
    assert calls == [1, 2, 3]
    assert (tmp_path / "cut" / "session.mcap").is_file()
    assert not (tmp_path / "cut" / "results.json").exists()


# --- solve --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", OUTSIDE)
def test_solve_outside_sessions_equals_the_command_line(name, tmp_path):
    calls = []
    results = geocal.solve(session(name), progress=lambda d, t: calls.append((d, t)))
    assert_steady_progress(calls)
    # In bytes of the file read, and one more step for the solve.
    assert calls[-1][1] == os.path.getsize(session(name)) + 1
    assert results.to_json() == cli_solve_file(session(name), tmp_path / "r.json")
    assert results.text == cli("solve", session(name)).stdout
    assert results.parameters.num_rows > 0


def test_results_tables_hold_the_json_numbers():
    results = geocal.solve(session("outside-clean-7"))
    data = results.data
    # The 21 geometric errors: 18 error functions along the axes, 3 squareness.
    ef = results.error_functions.to_pandas()
    assert len(ef.groupby(["axis", "error_function"])) == 18
    for axis, a in data["geometric_errors"]["axes"].items():
        for name, e in a["errors"].items():
            curve = results.error_function(name, axis=axis)
            np.testing.assert_array_equal(curve["position"], a["positions_m"])
            want = np.array([np.nan if v is None else v for v in e["values"]], dtype=float)
            np.testing.assert_array_equal(curve["value"], want)
            sigma = np.array([np.nan if v is None else v for v in e["sigma"]], dtype=float)
            np.testing.assert_array_equal(curve["sigma"], sigma)
    params = results.parameters.to_pandas()
    squareness = params[params["category"] == "squareness"].set_index("name")
    assert len(squareness) == 3
    for name, s in data["geometric_errors"]["squareness"].items():
        assert squareness.loc[name, "value"] == s["value_rad"]
        assert squareness.loc[name, "sigma"] == s["sigma_rad"]
    points = results.points.to_pandas()
    assert len(points) == len(data["points"])
    for row, p in zip(points.itertuples(), data["points"]):
        assert (row.error_x_m, row.error_y_m, row.error_z_m) == tuple(p["error_m"])
        assert (row.sigma_x_m, row.sigma_y_m, row.sigma_z_m) == tuple(p["sigma_m"])
    # polars takes the same tables.
    import polars as pl

    assert pl.from_arrow(results.points).height == len(data["points"])


def test_covariances_are_numpy_arrays():
    results = geocal.solve(session("outside-hexapod-clean-2"))
    covariances = results.covariances()
    assert covariances, "hexapod results hold the hinges' covariance"
    for name, c in covariances.items():
        assert isinstance(c, np.ndarray) and c.ndim == 2 and c.shape[0] == c.shape[1], name
        # The core's own matrix, symmetric to its rounding.
        np.testing.assert_allclose(c, c.T, rtol=0, atol=1e-12 * np.abs(c).max())
    np.testing.assert_array_equal(
        covariances["covariance_m2"], np.array(results.data["covariance_m2"])
    )


def test_solve_with_effects_equals_the_command_line(tmp_path):
    path = session("outside-reversal-8")
    results = geocal.solve(path, effects=["reversal"])
    assert results.to_json() == cli_solve_file(
        path, tmp_path / "r.json", "--effects", "reversal"
    )


# --- diagnose -----------------------------------------------------------------------------


# The tracer network's diagnosis on a rotary table's session (the multilateration one, several
# times slower, is the example notebook's) and a residual-model kind's.
@pytest.mark.parametrize(
    "name, effect",
    [
        ("outside-rotary-eccentricity-21", "tracer_eccentricity"),
        ("outside-probe-scale-21", None),
    ],
)
def test_diagnose_equals_the_command_line(name, effect):
    calls = []
    diagnosis = geocal.diagnose(session(name), progress=lambda d, t: calls.append((d, t)))
    assert diagnosis.to_json() + "\n" == cli("diagnose", session(name), "--json").stdout
    assert diagnosis.text == cli("diagnose", session(name)).stdout
    assert_steady_progress(calls)
    with open(os.path.join(SESSIONS, name, "truth.json"), encoding="utf-8") as f:
        truth = json.load(f)
    if effect is not None:
        assert diagnosis.selected == [effect]
    assert diagnosis.selected == truth.get("vocabulary_effects", diagnosis.selected)
    assert diagnosis.candidates().num_rows == len(diagnosis.data["candidates"])


# --- compare ------------------------------------------------------------------------------


def test_compare_equals_the_command_line(tmp_path):
    a = tmp_path / "a.json"
    b = tmp_path / "b.json"
    cli_solve_file(session("outside-clean-7"), a)
    cli_solve_file(session("outside-reversal-8"), b)
    comparison = geocal.compare(a, b)
    assert comparison.to_json() + "\n" == cli("compare", str(a), str(b), "--json").stdout
    assert comparison.text == cli("compare", str(a), str(b)).stdout
    assert comparison.table().num_rows == comparison.data["compared"]
    assert comparison.data["significant"], "a reversal of 6 µm is a change"
    loaded = geocal.load_results(a)
    assert loaded.to_json() == a.read_text(encoding="utf-8")


# --- errors -------------------------------------------------------------------------------


def test_errors_carry_the_command_lines_message(tmp_path):
    missing = str(tmp_path / "missing.mcap")
    with pytest.raises(geocal.GeocalError) as e:
        geocal.solve(missing)
    assert str(e.value) == cli_error("solve", missing)
    bad = tmp_path / "bad.toml"
    with open(DEMO, encoding="utf-8") as f:
        bad.write_text(f.read().replace("[plan]", "[plan]\nstaions = 3", 1))
    with pytest.raises(geocal.GeocalError) as e:
        geocal.check(bad)
    assert str(e.value) == cli_error("check", str(bad))
    assert "staions" in str(e.value)
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all")
    with pytest.raises(geocal.GeocalError) as e:
        geocal.read_session(garbage)
    assert "not an MCAP file" in str(e.value)


# --- the GIL --------------------------------------------------------------------------------


def test_solve_releases_the_gil():
    log = []
    worker = threading.Thread(
        target=lambda: geocal.solve(
            session("outside-clean-7"), progress=lambda d, t: log.append(("solve", d))
        )
    )
    worker.start()
    while worker.is_alive():
        log.append(("main", None))
        worker.join(0.002)
    solving = [k for k, (who, _) in enumerate(log) if who == "solve"]
    begin, end = solving[0], solving[-1]
    # Python ran in this thread while the Rust core solved in the other.
    assert ("main", None) in log[begin:end], "the GIL was held during the solve"


# --- sessions as Arrow against the mcap package -------------------------------------------------


def mcap_messages(path):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            yield channel.topic, message.log_time, message.publish_time, message.data


def by_topic(path):
    topics = {}
    for topic, log_time, publish_time, data in mcap_messages(path):
        topics.setdefault(topic, []).append((log_time, publish_time, json.loads(data)))
    return topics


def assert_column(batch, name, values, dtype):
    np.testing.assert_array_equal(
        batch.column(name).to_numpy(zero_copy_only=False), np.array(values, dtype=dtype)
    )


@pytest.mark.parametrize("name", ["outside-clean-7", "outside-rotary-clean-2"])
def test_arrow_arrays_equal_the_mcap_packages_reading(name):
    path = session(name)
    s = geocal.read_session(path)
    topics = by_topic(path)
    assert s.losses.complete and not s.losses.any
    header = topics["/geocal/session"][0][2]
    assert s.header["session_id"] == header["session_id"]
    assert s.kind == header["kind"]
    assert len(s.events) == len(topics["/run/event"])
    assert [e["event"]["kind"] for e in s.events] == [m[2]["kind"] for m in topics["/run/event"]]
    tracer_topics = [t for t in topics if t.startswith("/tracer/")]
    assert sorted(s.tracers) == sorted(t.split("/")[2] for t in tracer_topics)
    for topic in tracer_topics:
        batch = s.tracers[topic.split("/")[2]]
        msgs = topics[topic]
        assert batch.num_rows == len(msgs)
        assert_column(batch, "log_time_ns", [m[0] for m in msgs], np.uint64)
        assert_column(batch, "publish_time_ns", [m[1] for m in msgs], np.uint64)
        assert_column(batch, "seq", [m[2]["seq"] for m in msgs], np.uint64)
        assert_column(batch, "t_s", [m[2]["t_s"] for m in msgs], float)
        assert_column(batch, "length_m", [m[2]["length_m"] for m in msgs], float)
        assert_column(batch, "signal", [m[2].get("signal", 1.0) for m in msgs], float)
        assert_column(batch, "tracking", [m[2].get("tracking", True) for m in msgs], bool)
        # No per-sample Python objects: the lengths are one contiguous float64 buffer.
        lengths = s.arrays(batch)["length_m"]
        assert lengths.dtype == np.float64 and lengths.flags["C_CONTIGUOUS"]
    for topic in [t for t in topics if t.startswith("/env/")]:
        batch = s.env[topic.split("/")[2]]
        msgs = topics[topic]
        assert_column(batch, "air_temp_k", [m[2]["air_temp_k"] for m in msgs], float)
        assert_column(batch, "pressure_pa", [m[2]["pressure_pa"] for m in msgs], float)
        assert_column(batch, "humidity_pct", [m[2]["humidity_pct"] for m in msgs], float)
    for topic in [t for t in topics if t.startswith("/rotary/")]:
        batch = s.rotary[topic.split("/")[2]]
        msgs = topics[topic]
        assert_column(batch, "commanded_rad", [m[2]["commanded_rad"] for m in msgs], float)
        assert batch.column("encoder_rad").to_pylist() == [
            m[2].get("encoder_rad") for m in msgs
        ]
    stations = s.stations()
    assert stations and all(st["end_ns"] is not None for st in stations)
    first = s.station_samples(stations[0]["station"], tracer=sorted(s.tracers)[0])
    assert 0 < first.num_rows < s.tracers[sorted(s.tracers)[0]].num_rows


def test_kind_topics_as_json():
    path = session("outside-hexapod-clean-2")
    s = geocal.read_session(path)
    topics = by_topic(path)
    assert s.topics, "a hexapod session's own topics"
    for topic, batch in s.topics.items():
        assert [json.loads(t) for t in batch.column("json").to_pylist()] == [
            m[2] for m in topics[topic]
        ]


# --- damaged files ----------------------------------------------------------------------------


def damaged_copy(tmp_path):
    """outside-clean-7 with bytes of a middle chunk overwritten (its CRC then fails)."""
    from mcap.reader import make_reader

    source = session("outside-clean-7")
    with open(source, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 3, "a session of several chunks"
    chunk = chunks[1]
    data = bytearray(open(source, "rb").read())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle : middle + 64] = bytes(64)
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    return path, chunk


def test_a_damaged_file_reads_as_the_command_line_reads_it(tmp_path):
    path, chunk = damaged_copy(tmp_path)
    s = geocal.read_session(path)
    clean = geocal.read_session(session("outside-clean-7"))
    assert s.losses.any and s.losses.complete
    assert len(s.losses.damaged) == 1
    lost = s.losses.damaged[0]
    assert lost["byte_offset"] == chunk.chunk_start_offset
    kept = sum(b.num_rows for b in s.tracers.values())
    total = sum(b.num_rows for b in clean.tracers.values())
    assert 0 < kept < total
    # What the repaired copy holds, read by the mcap package: the same tracer samples.
    repaired = tmp_path / "repaired.mcap"
    cli("repair", str(path), "--out", str(repaired))
    copied = [(t, d) for t, _, _, d in mcap_messages(repaired)]
    assert sum(1 for t, _ in copied if t.startswith("/tracer/")) == kept
    if lost["messages"] is not None:
        # The repair adds a `data_lost` event for each loss.
        notes = sum(
            1 for t, d in copied if t == "/run/event" and json.loads(d)["kind"] == "data_lost"
        )
        assert notes == 1
        all_messages = sum(1 for _ in mcap_messages(session("outside-clean-7")))
        assert lost["messages"] == all_messages - (len(copied) - notes)
    # The solve of the damaged file is the command line's.
    assert geocal.solve(path).to_json() == cli_solve_file(str(path), tmp_path / "r.json")


def test_a_truncated_file_says_where_it_ends(tmp_path):
    data = open(session("outside-sphere-clean-2"), "rb").read()
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: len(data) * 2 // 3])
    s = geocal.read_session(path)
    assert not s.losses.complete
    assert 0 < s.losses.truncated["bytes_read"] <= len(data) * 2 // 3
    assert s.losses.truncated["file_bytes"] == len(data) * 2 // 3


# --- the wheel ------------------------------------------------------------------------------


def test_the_wheel_declares_its_dependencies_and_imports_with_only_python(tmp_path):
    wheel = os.environ["GEOCAL_WHEEL"]
    assert "abi3" in os.path.basename(wheel)
    with zipfile.ZipFile(wheel) as z:
        metadata = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        requires = [
            line.split(":", 1)[1].strip()
            for line in z.read(metadata).decode().splitlines()
            if line.startswith("Requires-Dist:")
        ]
        names = z.namelist()
    assert any(r.startswith("numpy") for r in requires), requires
    assert any(r.startswith("pyarrow") for r in requires), requires
    assert "geocal/_geocal.pyi" in names and "geocal/py.typed" in names
    bare = os.environ["GEOCAL_BARE_PYTHON"]
    script = (
        "import sys, geocal; c = geocal.check(sys.argv[1]); "
        "assert 'geocal' in sys.modules and 'pyarrow' not in sys.modules; "
        "print(c.to_json())"
    )
    done = subprocess.run([bare, "-c", script, DEMO], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout == cli("check", DEMO, "--json").stdout


# --- the example notebook ---------------------------------------------------------------------


def test_the_example_notebook_runs_end_to_end(tmp_path):
    import nbformat
    from nbclient import NotebookClient

    # The kernel's own inline backend draws the figures as PNG outputs.
    os.environ.pop("MPLBACKEND", None)
    source = os.path.join(REPO, "examples", "python", "geocal.ipynb")
    notebook = nbformat.read(source, as_version=4)
    client = NotebookClient(
        notebook,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},
    )
    client.execute()
    outputs = [o for c in notebook.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 2, "the station's lengths and the 21 error functions"
