"""Argument types of the ``stircasadi`` command: each value is checked as it is parsed.

When to use: as ``type=`` of an ``argparse`` option, so that a bad value stops the command before
any work with one line saying what was wrong and what is allowed (argparse prints it as
``stircasadi CMD: error: argument --seed: ...`` and the command exits with status 2). Input files
are checked here too (a capture that does not exist, is a folder or is not HDF5); output paths
are checked by ``stircasadi.io.check_output`` in the commands, before the long work starts.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["Formatter", "SEED_MAX", "HIDDEN_MAX", "BOUNCES_MAX", "seed", "hidden", "bounces",
           "problem", "input_file", "capture_file", "estimate_file", "areas", "kind_of",
           "time_limit", "TIME_LIMIT_DEFAULT", "nlos_option"]

#: random seeds go to ``numpy.random.default_rng``; the CLI keeps them to 32 bits so that a
#: seed written in a report can be typed back everywhere (0 ... 2**32 - 1)
SEED_MAX = 2 ** 32 - 1
#: the most hidden patches ``--hidden`` may ask for (each adds a search step and 6 unknowns)
HIDDEN_MAX = 64
#: the highest finite bounce order ``--bounces`` takes ("all" sums every order)
BOUNCES_MAX = 32

#: the estimate's wall-clock limit when --time-limit is not given (seconds): the largest listed
#: problem (three_planes, 147 patches) needs 6.5 min on an idle 2-core machine, 17 min shared
TIME_LIMIT_DEFAULT = 1800.0

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


class Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help with every option's default shown and descriptions kept as written."""


def _int(text: str, what: str, lo: int, hi: int, meaning: str) -> int:
    try:
        v = int(str(text).strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be a whole number from {lo} to {hi} ({meaning}); "
                                         f"got {text!r}.") from None
    if not lo <= v <= hi:
        raise argparse.ArgumentTypeError(f"{what} must be from {lo} to {hi} ({meaning}); got {v}.")
    return v


def seed(text: str) -> int:
    """A random seed: an integer from 0 to ``SEED_MAX``."""
    return _int(text, "the seed", 0, SEED_MAX, "a random seed; the same seed gives the same noise")


def hidden(text: str) -> int:
    """A number of hidden patches: 0 ... ``HIDDEN_MAX``."""
    return _int(text, "the number of hidden patches", 0, HIDDEN_MAX,
                "omit --hidden to let the data decide")


def time_limit(text: str) -> float | None:
    """A wall-clock limit in seconds (> 0), or 0 / ``none`` for no limit (returned as None)."""
    t = str(text).strip().lower()
    if t in ("0", "none", "inf"):
        return None
    try:
        v = float(t.rstrip("s"))
    except ValueError:
        v = float("nan")
    if not (v > 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"--time-limit must be a number of seconds > 0, or 0 for no limit; "
                                         f"got {text!r}.")
    return v


def bounces(text: str):
    """A bounce order: an integer 1 ... ``BOUNCES_MAX`` or ``all``."""
    if str(text).strip().lower() == "all":
        return "all"
    return _int(text, "the bounce order", 1, BOUNCES_MAX, "or 'all' for every order")


def problem(text: str) -> str:
    """A problem name (``stircasadi problems``) or a path to a problem script; checked now."""
    from ..errors import StircasadiError
    from ..problem import load_problem

    try:
        load_problem(text)
    except StircasadiError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def input_file(text: str, what: str = "input") -> Path:
    """An existing, readable file (not a folder)."""
    p = Path(text).expanduser()
    if not p.exists():
        raise argparse.ArgumentTypeError(f"the {what} file {p} does not exist; check the path.")
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{p} is a folder; give the {what} file inside it.")
    try:
        with open(p, "rb") as f:
            f.read(8)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"the {what} file {p} cannot be read: "
                                         f"{exc.strerror or exc}.") from None
    return p


def kind_of(path: Path) -> str:
    """``"capture"`` (an HDF5 file), ``"estimate"`` (a JSON object) or ``"unknown"``, by content."""
    with open(path, "rb") as f:
        head = f.read(512)
    if head.startswith(_HDF5_SIGNATURE):
        return "capture"
    if head.lstrip()[:1] == b"{":
        return "estimate"
    return "unknown"


def capture_file(text: str) -> Path:
    """An existing Capture file (HDF5 by its signature; its fields are checked when it is read)."""
    p = input_file(text, "capture")
    if kind_of(p) != "capture":
        raise argparse.ArgumentTypeError(
            f"{p} is not an HDF5 file, so not a Capture; convert other recordings with "
            "'stircasadi import FILE --out capture.h5'.")
    return p


def estimate_file(text: str) -> Path:
    """An existing estimate.json file."""
    p = input_file(text, "estimate")
    if kind_of(p) != "estimate":
        raise argparse.ArgumentTypeError(f"{p} is not a JSON object, so not an estimate.json.")
    return p


def areas(text: str) -> dict:
    """Declared areas: a JSON object {patch id: m^2}, inline or in a .json file."""
    p = Path(text).expanduser()
    try:
        raw = p.read_text() if (p.suffix.lower() == ".json" or p.is_file()) else text
        d = json.loads(raw)
        if not isinstance(d, dict):
            raise ValueError("not a JSON object")
        out = {int(k): float(a) for k, a in d.items()}
    except (OSError, ValueError, TypeError) as exc:
        raise argparse.ArgumentTypeError(
            f"--areas must be a JSON object {{patch id: area in m^2}} such as '{{\"0\": 0.01}}', or a "
            f".json file holding one; got {text!r} ({exc}).") from None
    bad = {k: v for k, v in out.items() if not (v > 0 and v < float("inf")) or k < 0}
    if bad:
        raise argparse.ArgumentTypeError(f"--areas needs patch ids >= 0 and areas > 0 m^2; got {bad}.")
    return out


def nlos_option(text: str) -> tuple:
    """One ``--nlos KEY=VALUE`` option of the relay-wall reconstructions (``stircasadi.nlos``):
    the value read as JSON where it parses (numbers, true / false, null, "text", [lists]), a
    comma-separated list of numbers as a tuple (``extent=-0.2,0.2,-0.2,0.2``), else as text
    (``prior=auto``). Which keys exist is checked by the reconstruction, which lists them."""
    key, sep, raw = str(text).partition("=")
    key = key.strip()
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(
            f"--nlos takes KEY=VALUE, a field of stircasadi.nlos VolumeSettings / SurfaceSettings or "
            f"init / wall_step / gain (e.g. --nlos n_nodes=16 --nlos prior=auto --nlos wall_step=4); "
            f"got {text!r}.")
    raw = raw.strip()
    try:
        val = json.loads(raw)
    except ValueError:
        parts = [q.strip() for q in raw.split(",")]
        try:
            val = tuple(float(q) for q in parts) if len(parts) > 1 else raw
        except ValueError:
            val = raw
    if isinstance(val, list):
        val = tuple(val)
    return key, val
