"""geocal from Python: read calibration sessions into Arrow and NumPy, solve, diagnose, check,
compare and run plans, with the same Rust core as the ``geocal`` command line.

Every result's ``to_json()`` is the command line's JSON text to the byte; its tables are
``pyarrow.RecordBatch`` objects (``.to_pandas()``, ``polars.from_arrow(...)``); errors are
:class:`GeocalError` carrying the command line's message. Long calls release the GIL and
take an optional ``progress(done, total)`` callback.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Union

from . import _geocal
from ._geocal import GeocalError

__all__ = [
    "GeocalError",
    "Session",
    "Losses",
    "Results",
    "Diagnosis",
    "PlanCheck",
    "Comparison",
    "RunOutput",
    "read_session",
    "solve",
    "diagnose",
    "check",
    "compare",
    "run",
    "load_results",
]

__version__: str = _geocal.__version__

PathLike = Union[str, "os.PathLike[str]"]
Progress = Optional[Callable[[int, int], Any]]


def _path(p: PathLike) -> str:
    return os.fspath(p)


@dataclass(frozen=True)
class Losses:
    """What the reader could not read, as ``geocal solve`` and ``geocal repair`` report it.

    ``complete``: the file ends with its footer; otherwise ``truncated`` holds ``bytes_read``,
    ``file_bytes``, ``messages_read`` and ``reason``. ``damaged``: the chunks skipped (byte
    offset and length, the log-time range lost, messages lost, reason). ``lost_before_repair``:
    spans a repaired copy's original had lost. ``skipped``: messages on known topics that did
    not parse; ``ignored``: messages on topics the reader does not know.
    """

    complete: bool
    truncated: Optional[Dict[str, Any]]
    damaged: List[Dict[str, Any]]
    lost_before_repair: List[Dict[str, Any]]
    skipped: int
    ignored: int

    @property
    def any(self) -> bool:
        """Whether anything was lost."""
        return (
            not self.complete
            or bool(self.damaged)
            or bool(self.lost_before_repair)
            or self.skipped > 0
        )


@dataclass
class Session:
    """A recorded session (``geocal-session/1``), read as the command line reads it.

    ``tracers``, ``env``, ``rotary``, ``machines``, ``probes``: device id -> its samples as a
    ``pyarrow.RecordBatch`` (columns ``log_time_ns``, ``publish_time_ns`` then the message's
    fields in SI units). ``topics``: a plan kind's own topics -> ``log_time_ns``,
    ``publish_time_ns``, ``json``. ``events``: the run events, each
    ``{"log_time_ns", "publish_time_ns", "event"}``.
    """

    path: str
    header: Dict[str, Any]
    events: List[Dict[str, Any]]
    losses: Losses
    tracers: Dict[str, Any]
    env: Dict[str, Any]
    rotary: Dict[str, Any]
    machines: Dict[str, Any]
    probes: Dict[str, Any]
    topics: Dict[str, Any]

    @property
    def kind(self) -> str:
        """The plan kind of the session header."""
        return self.header["kind"]

    def arrays(self, batch: Any) -> Dict[str, Any]:
        """A record batch's columns as NumPy arrays (without copies where Arrow allows)."""
        out = {}
        for name, column in zip(batch.schema.names, batch.columns):
            try:
                out[name] = column.to_numpy(zero_copy_only=True)
            except Exception:  # nulls, booleans, strings and lists need a copy
                out[name] = column.to_numpy(zero_copy_only=False)
        return out

    def stations(self) -> List[Dict[str, Any]]:
        """Each station's span from its ``station_begin`` to its ``station_end`` event:
        ``{"station", "station_index", "begin_ns", "end_ns"}``, in order."""
        spans: List[Dict[str, Any]] = []
        for e in self.events:
            ev = e["event"]
            if ev.get("kind") == "station_begin":
                spans.append(
                    {
                        "station": ev["station"],
                        "station_index": ev.get("station_index"),
                        "begin_ns": e["log_time_ns"],
                        "end_ns": None,
                    }
                )
            elif ev.get("kind") == "station_end":
                for s in reversed(spans):
                    if s["station"] == ev["station"] and s["end_ns"] is None:
                        s["end_ns"] = e["log_time_ns"]
                        break
        return spans

    def station_samples(self, station: str, tracer: Optional[str] = None) -> Any:
        """The tracer samples recorded while ``station`` was set up (a ``RecordBatch``)."""
        import pyarrow.compute as pc

        if tracer is None:
            if len(self.tracers) != 1:
                raise GeocalError(
                    f"{self.path}: name the tracer, the session has {sorted(self.tracers)}"
                )
            tracer = next(iter(self.tracers))
        batch = self.tracers[tracer]
        spans = [s for s in self.stations() if s["station"] == station]
        if not spans:
            raise GeocalError(f"{self.path}: no station {station!r} in the run events")
        t = batch.column("log_time_ns")
        mask = None
        for s in spans:
            end = s["end_ns"] if s["end_ns"] is not None else 2**64 - 1
            m = pc.and_(pc.greater_equal(t, s["begin_ns"]), pc.less_equal(t, end))
            mask = m if mask is None else pc.or_(mask, m)
        return batch.filter(mask)


def read_session(path: PathLike) -> Session:
    """Read a session file as ``geocal solve`` reads it: a damaged or truncated file is read
    up to and around its damage, and :attr:`Session.losses` says what was lost."""
    raw = _geocal.read_session(_path(path))
    losses = json.loads(raw["losses_json"])
    completeness = losses["completeness"]
    return Session(
        path=_path(path),
        header=json.loads(raw["header_json"]),
        events=json.loads(raw["events_json"]),
        losses=Losses(
            complete=completeness["complete"],
            truncated=None if completeness["complete"] else completeness,
            damaged=losses["damaged"],
            lost_before_repair=losses["lost_before_repair"],
            skipped=losses["skipped"],
            ignored=losses["ignored"],
        ),
        tracers=raw["tracers"],
        env=raw["env"],
        rotary=raw["rotary"],
        machines=raw["machines"],
        probes=raw["probes"],
        topics=raw["topics"],
    )


def _covariances(value: Any, prefix: str = "") -> Dict[str, Any]:
    import numpy as np

    found: Dict[str, Any] = {}
    if isinstance(value, dict):
        for key, v in value.items():
            name = f"{prefix}.{key}" if prefix else key
            if "covariance" in key and isinstance(v, list):
                found[name] = np.array(v, dtype=float)
            else:
                found.update(_covariances(v, name))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            found.update(_covariances(v, f"{prefix}[{i}]"))
    return found


@dataclass
class _CommandOutput:
    """What a command prints: its JSON (``data`` parsed) and its text report."""

    json_text: str
    text: Optional[str]
    data: Dict[str, Any] = field(init=False)

    def __post_init__(self) -> None:
        self.data = json.loads(self.json_text)

    def to_json(self) -> str:
        """The command's JSON exactly as the command line writes it (``--out FILE`` for
        results; ``--json`` without its final newline for the others)."""
        return self.json_text


@dataclass
class Results(_CommandOutput):
    """A calibration's results (``geocal-results/1``) of any plan kind.

    ``parameters`` (every estimate with its σ), ``points`` (nominal, error and σ per axis) and
    ``error_functions`` (the 21 error functions at their positions with σ, a table's angular
    error, ...) are ``pyarrow.RecordBatch`` tables with the fleet export's columns
    (docs/fleet.md); ``data`` is the parsed JSON; ``text`` the command line's report.
    """

    parameters: Any
    points: Any
    error_functions: Any

    @property
    def kind(self) -> str:
        return self.data["kind"]

    def covariances(self) -> Dict[str, Any]:
        """Every covariance matrix the results hold, as NumPy arrays by their JSON path
        (a rotary axis's location, a sphere centre's, hexapod hinges'). Multilateration
        results carry σ per coordinate (``points``, ``parameters``), not a full covariance."""
        return _covariances(self.data)

    def error_function(self, name: str, axis: Optional[str] = None) -> Dict[str, Any]:
        """One error function (e.g. ``"EXX"``) as NumPy arrays: ``position``, ``value``,
        ``sigma`` (NaN where not identifiable)."""
        import numpy as np

        t = self.error_functions.to_pandas()
        t = t[t["error_function"] == name]
        if axis is not None:
            t = t[t["axis"] == axis]
        if t.empty:
            raise GeocalError(f"the results have no error function {name!r}")
        return {
            "position": t["position"].to_numpy(dtype=float),
            "value": t["value"].to_numpy(dtype=float, na_value=np.nan),
            "sigma": t["sigma"].to_numpy(dtype=float, na_value=np.nan),
        }


def _results(json_text: str, text: Optional[str], tables: Dict[str, Any]) -> Results:
    return Results(
        json_text=json_text,
        text=text,
        parameters=tables["parameters"],
        points=tables["points"],
        error_functions=tables["error_functions"],
    )


def load_results(path: PathLike) -> Results:
    """A results file (a run folder's ``results.json``) as :class:`Results` (no text report)."""
    with open(_path(path), encoding="utf-8") as f:
        text = f.read()
    return _results(text, None, _geocal.results_tables(text))


def solve(
    path: PathLike, effects: Optional[Sequence[str]] = None, progress: Progress = None
) -> Results:
    """Solve a recorded session as ``geocal solve [--effects ...] SESSION`` does, for every
    plan kind; ``effects`` are fitted jointly (names as :func:`diagnose` gives them)."""
    json_text, text, tables = _geocal.solve(
        _path(path), list(effects) if effects is not None else None, progress
    )
    return _results(json_text, text, tables)


@dataclass
class Diagnosis(_CommandOutput):
    """The sim-to-real gap diagnosis of a session (``geocal diagnose``)."""

    @property
    def selected(self) -> List[str]:
        """The effects the diagnosis selected (names ``solve(effects=...)`` takes)."""
        return [e if isinstance(e, str) else e["effect"] for e in self.data.get("selected", [])]

    def candidates(self) -> Any:
        """The candidate effects with their statistics as a ``pyarrow.Table``: one row per
        candidate, its scalar statistics and its fitted parameters as ``param.<name>``."""
        import pyarrow as pa

        rows = []
        for c in self.data.get("candidates", []):
            row = {k: v for k, v in c.items() if not isinstance(v, (dict, list))}
            for name, value in (c.get("params") or {}).items():
                row[f"param.{name}"] = value
            rows.append(row)
        return pa.Table.from_pylist(rows)


def diagnose(path: PathLike, progress: Progress = None) -> Diagnosis:
    """Diagnose a recorded session as ``geocal diagnose SESSION`` does."""
    json_text, text = _geocal.diagnose(_path(path), progress)
    return Diagnosis(json_text=json_text, text=text)


@dataclass
class PlanCheck(_CommandOutput):
    """What a plan predicts before it runs (``geocal check``)."""


def check(config: PathLike) -> PlanCheck:
    """Validate a configuration and predict its uncertainties, as ``geocal check`` does."""
    json_text, text = _geocal.check(_path(config))
    return PlanCheck(json_text=json_text, text=text)


@dataclass
class Comparison(_CommandOutput):
    """Whether a machine changed between two runs (``geocal compare``, ``geocal-compare/1``)."""

    def table(self) -> Any:
        """One row per parameter compared, as a ``pyarrow.Table``."""
        import pyarrow as pa

        rows = [
            {k: v for k, v in p.items() if not isinstance(v, (dict, list))}
            for p in self.data.get("parameters", [])
        ]
        return pa.Table.from_pylist(rows)


def compare(
    a: PathLike,
    b: PathLike,
    alpha: float = 0.05,
    tolerance_m: Optional[float] = None,
    tolerance_rad: Optional[float] = None,
    tolerance_other: Optional[float] = None,
) -> Comparison:
    """Compare two runs (run folders or results files) as ``geocal compare A B`` does."""
    json_text, text = _geocal.compare(
        _path(a), _path(b), alpha, tolerance_m, tolerance_rad, tolerance_other
    )
    return Comparison(json_text=json_text, text=text)


@dataclass
class RunOutput:
    """A finished run: where its session and results are, and the results."""

    session_path: str
    results_path: str
    recorded: str
    results: Results


def run(
    config: PathLike,
    out: PathLike,
    truth: Optional[PathLike] = None,
    progress: Progress = None,
) -> RunOutput:
    """Run a plan of any kind (simulated, emulated or real devices) as ``geocal run CONFIG
    --out OUT`` does: record ``OUT/session.mcap``, solve it, write ``OUT/results.json``.
    ``progress(done, total)`` is called as the run goes; an exception it raises (or Ctrl-C)
    cancels the run, which stays resumable (``geocal run --resume OUT``)."""
    raw = _geocal.run(
        _path(config), _path(out), None if truth is None else _path(truth), progress
    )
    return RunOutput(
        session_path=os.fspath(raw["session_path"]),
        results_path=os.fspath(raw["results_path"]),
        recorded=raw["recorded"],
        results=_results(raw["results_json"], raw["text"], raw["tables"]),
    )
