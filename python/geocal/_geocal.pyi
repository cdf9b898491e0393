"""Type stubs of the native module ``geocal._geocal`` (the Rust core). Use the package
``geocal``: it wraps these calls in typed objects."""

from typing import Any, Callable, Dict, List, Optional, Tuple

import pyarrow

__version__: str

class GeocalError(Exception):
    """A geocal command failed; the message is the command line's (causes on ``because:``
    lines)."""

_Progress = Optional[Callable[[int, int], Any]]

def read_session(path: str) -> Dict[str, Any]:
    """``header_json``, ``events_json``, ``losses_json`` (str) and ``tracers``, ``env``,
    ``rotary``, ``machines``, ``probes``, ``topics``: id -> ``pyarrow.RecordBatch``."""

def solve(
    path: str, effects: Optional[List[str]] = None, progress: _Progress = None
) -> Tuple[str, str, Dict[str, pyarrow.RecordBatch]]:
    """(results JSON as ``geocal solve --out`` writes it, text report, tables)."""

def results_tables(json: str) -> Dict[str, pyarrow.RecordBatch]:
    """``parameters``, ``points``, ``error_functions`` of a results document."""

def diagnose(path: str, progress: _Progress = None) -> Tuple[str, str]:
    """(diagnosis JSON as ``geocal diagnose --json`` prints it, text)."""

def check(config: str) -> Tuple[str, str]:
    """(plan check JSON as ``geocal check --json`` prints it, text)."""

def compare(
    a: str,
    b: str,
    alpha: float = 0.05,
    tolerance_m: Optional[float] = None,
    tolerance_rad: Optional[float] = None,
    tolerance_other: Optional[float] = None,
) -> Tuple[str, str]:
    """(``geocal-compare/1`` JSON as ``geocal compare --json`` prints it, text)."""

def run(
    config: str, out: str, truth: Optional[str] = None, progress: _Progress = None
) -> Dict[str, Any]:
    """``session_path``, ``results_path``, ``results_json``, ``text``, ``recorded``,
    ``tables``."""
