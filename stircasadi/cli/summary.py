"""What the commands print after the table: a short account of the estimate, the timings once.

``summary_lines(d)`` reads only the estimate.json dict (schema v2, docs/estimate-json.md): how
many patches were found, where the hidden ones are, how well the model fits (chi2/dof, noise),
what the data could not identify and why, which checks passed, the ambiguities, the verdict.
``timing_line`` prints every stage once with its unit.
"""
from __future__ import annotations

import math

__all__ = ["summary_lines", "print_summary", "timing_line", "estimate_stage_times"]

_WIDTH = 160


def _short(text: str, n: int = _WIDTH) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 1] + "…"


def _xyz(p) -> str:
    v = p.get("position")
    if not v or any(x is None for x in v):
        return "position not identified"
    s = p.get("position_std")
    sd = (f" ± {math.sqrt(sum(x * x for x in s)) * 1e3:.2g} mm"
          if s and all(x is not None for x in s) else "")
    return f"({v[0]:.3f}, {v[1]:.3f}, {v[2]:.3f}) m{sd}"


def summary_lines(d: dict, names: dict | None = None) -> list[str]:
    """The account of an estimate (see the module docstring); ``names``: {id: label}."""
    pats = d.get("patches") or []
    nm = names or {}
    label = {p["id"]: nm.get(p["id"], p.get("name") or str(p["id"])) for p in pats}
    vis = [p for p in pats if p.get("visible", True)]
    hid = [p for p in pats if not p.get("visible", True)]
    out = [f"found: {len(vis)} visible and {len(hid)} hidden patches (positions in the "
           f"{d.get('frame', 'capture')} frame)"]
    for p in hid[:6]:
        extra = []
        if p.get("albedo") is not None:
            extra.append(f"albedo {p['albedo']:.3f}")
        if p.get("albedo_area") is not None:
            s = p.get("albedo_area_std")
            extra.append(f"albedo·area {p['albedo_area'] * 1e4:.3g}" + (f" ± {s * 1e4:.2g}" if s else "")
                         + " cm²")
        out.append(f"  hidden {label[p['id']]}: {_xyz(p)}" + (", " + ", ".join(extra) if extra else ""))
    if len(hid) > 6:
        out.append(f"  ... and {len(hid) - 6} more hidden patches")
    c2 = d.get("chi2_dof")
    noise = d.get("noise") or {}
    if c2 is not None:
        out.append(f"fit: whitened χ²/dof {c2:.3g}" + (f"; noise σ {noise['sigma']:.2g} ({noise.get('source')})"
                                                      if noise.get("sigma") else ""))
    why: dict = {}
    for p in pats:
        for q in p.get("unidentifiable") or []:
            why.setdefault(q, []).append((label[p["id"]], (p.get("notes") or {}).get(q, "")))
    for q, who in why.items():
        first, reason = who[0]
        out.append(_short(f"not identified: {q} of {', '.join(w for w, _ in who[:8])}"
                          f"{' …' if len(who) > 8 else ''}" + (f" ({first}: {reason})" if reason else "")))
    checks = d.get("checks") or []
    if checks:
        bad = [c for c in checks if not c.get("passed")]
        out.append(f"checks against the data: {len(checks) - len(bad)} of {len(checks)} passed"
                   + ("" if bad else f" ({', '.join(dict.fromkeys(c['name'] for c in checks))})"))
        for c in bad:
            out.append(_short(f"  FAILED {c['name']}: {c.get('message', '')}"))
    amb = [a for a in d.get("ambiguities") or [] if a.get("kind") != "note"]
    for a in amb[:3]:
        out.append(_short(f"ambiguity ({a.get('kind')}): {a.get('message', '')}"))
    if len(amb) > 3:
        out.append(f"... {len(amb) - 3} more ambiguities in estimate.json")
    verdict = d.get("verdict") or ("OK" if d.get("success") else "UNRELIABLE")
    reasons = d.get("reasons") or []
    out.append(f"verdict: {verdict}" + (" — " + _short("; ".join(reasons), 400) if reasons else ""))
    return out


def print_summary(d: dict, names: dict | None = None) -> None:
    print("\n".join(summary_lines(d, names)))


def estimate_stage_times(d: dict) -> dict:
    """{stage: seconds} of the estimate's stages, in pipeline order (``stages.*.wall_time_s``)."""
    out = {}
    for k, v in (d.get("stages") or {}).items():
        if k in ("geometry_total", "total") or not isinstance(v, dict):
            continue
        t = v.get("wall_time_s")
        if isinstance(t, (int, float)):
            out[k] = float(t)
    return out


def timing_line(timings: dict) -> str:
    """``timings (s): a 0.01 · b 1.2 (x 0.3, y 0.9) · total 2.2``; values are seconds or
    (seconds, {sub-stage: seconds})."""
    parts = []
    for k, v in timings.items():
        if isinstance(v, tuple):
            tot, sub = v
            inner = ", ".join(f"{a} {b:.2f}" for a, b in sub.items())
            parts.append(f"{k} {tot:.2f}" + (f" ({inner})" if inner else ""))
        else:
            parts.append(f"{k} {v:.2f}")
    return "timings (s): " + " · ".join(parts)
