"""The application commands, registered by ``stircasadi.cli`` through ``add_parsers(sub)``.

    stircasadi relight [CAPTURE] [--estimate EST.json] --out relit.h5 [--weights ...] [...]
    stircasadi separate CAPTURE --out separation.h5 [--nayar] [--layout ROWS,COLS]
    stircasadi segment EST.json --out segmentation.json [--level 0.01]
    stircasadi replace EST.json --out replaced.h5 (--ids 1,2 | --segmentation S --material K)
                       --brdf lambertian|phong --albedo A [--specular S --exponent N]
    stircasadi deconvolve RECORDS.h5 --out capture.h5      (or --emulate PROBLEM --code mls:9)

Errors are ``StircasadiError``: ``stircasadi.cli.main`` prints them as one line and exits 2.
Each command checks every output path before computing (an output equal to an input, a missing
folder: refused), writes its HDF5/JSON result atomically and, with ``--pictures DIR`` (default:
``<out>_pictures`` beside the result; ``--no-pictures`` to skip), PNG pictures.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..errors import StircasadiError
from ..io import check_output

__all__ = ["add_parsers"]


# ---------------------------------------------------------------------- argument parsing
def _floats(text, what):
    if text is None:
        return None
    try:
        return np.array([float(x) for x in str(text).split(",") if x.strip()])
    except ValueError:
        raise StircasadiError(f"--{what} must be comma-separated numbers such as 1,0.5,2; got {text!r}.") from None


def _ints(text, what):
    if text is None:
        return None
    try:
        return np.array([int(x) for x in str(text).split(",") if x.strip()], int)
    except ValueError:
        raise StircasadiError(f"--{what} must be comma-separated integers such as 0,2,5; got {text!r}.") from None


def _xyz(text, what):
    v = _floats(text, what)
    if v is not None and v.shape != (3,):
        raise StircasadiError(f"--{what} must be three numbers x,y,z in metres; got {text!r}.")
    return v


def _areas(items):
    out = {}
    for it in items or []:
        try:
            k, v = it.split("=")
            out[int(k)] = float(v)
        except ValueError:
            raise StircasadiError(f"--area must be ID=AREA (m^2), e.g. --area 4=0.01; got {it!r}.") from None
    return out


def _bounces(text):
    if text is None or text == "all":
        return text
    try:
        return int(text)
    except ValueError:
        raise StircasadiError(f"--bounces must be an integer >= 1 or 'all'; got {text!r}.") from None


def _outputs(args, inputs, suffixes):
    out = check_output(args.out, inputs=inputs, suffixes=suffixes)
    pics = None
    if not args.no_pictures:
        pics = Path(args.pictures) if args.pictures else out.with_name(out.stem + "_pictures")
        check_output(pics, inputs=inputs, what="pictures folder", folder=True)
    return out, pics


def _pictures_dir(pics):
    if pics is not None:
        pics.mkdir(parents=True, exist_ok=True)
    return pics


def _common(p, out_help, suffix):
    p.add_argument("--out", required=True, help=f"{out_help} (a {suffix} file; never one of the inputs)")
    p.add_argument("--pictures", default=None, metavar="DIR",
                   help="folder for PNG pictures (default: <out stem>_pictures beside --out)")
    p.add_argument("--no-pictures", action="store_true", help="write the result only, no pictures")


def _estimate_args(p, render: bool = False):
    if render:
        p.add_argument("--source", default=None, help="source position x,y,z (m, the estimate's frame; "
                                                      "default: the estimate's; needs --estimate)")
        p.add_argument("--camera", default=None, help="camera position x,y,z (m, the estimate's frame; "
                                                      "default: the estimate's; needs --estimate)")
        p.add_argument("--bin-width", type=float, default=0.005, help="bin width (m) when no capture gives one")
        p.add_argument("--no-std", action="store_true", help="skip the uncertainty propagation (one render)")
    p.add_argument("--area", action="append", metavar="ID=A",
                   help="declare the area (m^2) of a patch the estimate leaves null (repeatable)")
    p.add_argument("--exclude", default=None, metavar="IDS",
                   help="patch ids left out of the scene (e.g. ones the data cannot place)")
    p.add_argument("--allow-unreliable", action="store_true",
                   help="use an estimate whose verdict is UNRELIABLE (results are marked so)")


def _belief(args):
    from .belief import SceneBelief

    path = Path(args.estimate)
    if not path.exists():
        raise StircasadiError(f"Estimate file not found: {path}.")
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise StircasadiError(f"{path} is not a readable estimate.json ({exc}).") from exc
    ex = _ints(args.exclude, "exclude")
    return SceneBelief.from_estimate(d, areas=_areas(args.area), allow_unreliable=args.allow_unreliable,
                                     exclude=() if ex is None else ex.tolist())


def _capture(path):
    from ..capture import Capture

    return Capture.read(path)


def _sensor_of(cap):
    from ..irf import from_samples
    from ..sensor import Sensor

    if cap is None or cap.irf is None:
        return Sensor()
    return Sensor(irf=from_samples(cap.irf, cap.grid.bin_width))


# ---------------------------------------------------------------------- relight
def _illumination(args):
    from .relight import Illumination

    w = _floats(args.weights, "weights")
    ids = _ints(args.ids, "ids")
    if w is None:
        return None if ids is None else Illumination(np.ones(len(ids)), ids=ids,
                                                     delays=_floats(args.delays, "delays"),
                                                     pulses=_floats(args.pulse, "pulse"))
    return Illumination(w, ids=ids, delays=_floats(args.delays, "delays"), pulses=_floats(args.pulse, "pulse"))


def _run_relight(args) -> int:
    from . import pictures as pic
    from .records import write_result
    from .relight import Illumination, relight_capture
    from .render import RenderSettings, render

    if args.capture is None and args.estimate is None:
        raise StircasadiError("relight needs a CAPTURE (superposition of its STIR) or --estimate "
                              "(rendering from the estimate), or both.")
    ins = [x for x in (args.capture, args.estimate) if x]
    out, pics = _outputs(args, ins, (".h5",))
    cap = _capture(args.capture) if args.capture else None
    ill = _illumination(args)
    if args.estimate is None:
        if args.source is not None or args.camera is not None:
            raise StircasadiError("A new --source or --camera needs --estimate: the measured STIR only "
                                  "knows the capture's own source and camera.")
        ill = ill or Illumination(np.ones(len(cap.ill_ids())))
        r = relight_capture(cap, ill)
        summary = {"route": "superposition", "observed_ids": r.obs_ids, "steady": r.steady, **r.metadata}
        write_result(out, "relight", {"transient": r.transient, "steady": r.steady, "observed_ids": r.obs_ids},
                     summary, grid=r.grid)
        if _pictures_dir(pics):
            pic.bars(r.obs_ids, {"relit (steady state)": r.steady}, pics / "relit_steady.png",
                     title="relit by superposition of the measured STIR")
            allon = relight_capture(cap, Illumination(np.ones(len(cap.ill_ids()))))
            j = int(np.argmax(r.steady))
            pic.profiles(r.grid.centres, {f"patch {r.obs_ids[j]}: every patch lit": allon.transient[j],
                                          f"patch {r.obs_ids[j]}: relit": r.transient[j]},
                         pics / "profiles.png", title="time profile before/after")
        print(f"relight: superposition of {cap.stir.shape} -> {out}; steady state {np.round(r.steady, 6).tolist()[:8]}")
        return 0
    belief = _belief(args)
    sensor = _sensor_of(cap)
    settings = RenderSettings(bounces=_bounces(args.bounces),
                              bin_width=cap.grid.bin_width if cap is not None else args.bin_width,
                              with_std=not args.no_std)
    res = render(belief, sensor=sensor, source=args.source, camera=args.camera, illumination=ill,
                 settings=settings, legs_included=cap.legs_included if cap is not None else True)
    summary = {"route": "estimate", **res.metadata, "illuminated_ids": res.ill_ids, "observed_ids": res.obs_ids}
    write_result(out, "relight", {"stir": res.stir, "stir_std": res.stir_std, "steady": res.steady,
                                  "steady_std": res.steady_std, "transient": res.relit,
                                  "transient_std": res.relit_std, "relit_steady": res.relit_steady,
                                  "relit_steady_std": res.relit_steady_std,
                                  "illuminated_ids": res.ill_ids, "observed_ids": res.obs_ids},
                 summary, grid=res.grid)
    if _pictures_dir(pics):
        _render_pictures(belief, res, pics, "relit")
    print(f"relight: rendered the estimate ({belief.verdict}) -> {out}: {len(res.ill_ids)} lit x "
          f"{len(res.obs_ids)} seen, {res.grid.n_bins} bins, bounces {res.metadata['bounces']}")
    return 0


def _render_pictures(belief, res, pics, tag, before=None, focus=None):
    from . import pictures as pic

    sc = belief.scene_at(belief.values, source=res.metadata["source"], camera=res.metadata["camera"])
    idx = [belief.index(i) for i in res.obs_ids]
    vals = res.relit_steady if res.relit_steady is not None else res.steady.sum(axis=0)
    full = np.full(sc.n_patches, np.nan)
    full[idx] = vals
    pic.patch_image(sc.positions, sc.normals, sc.areas, full, sc.camera, pics / f"{tag}_image.png",
                    title=f"{tag}: steady state seen from {np.round(sc.camera, 3).tolist()}",
                    ids=belief.ids, log=True)
    curves, bands = {}, {}
    tr = res.relit if res.relit is not None else res.stir.sum(axis=0)
    sd = res.relit_std if res.relit is not None else None
    obs = [int(v) for v in res.obs_ids]
    j = obs.index(int(focus)) if focus is not None and int(focus) in obs else int(np.argmax(vals))
    if before is not None:
        btr = before.relit if before.relit is not None else before.stir.sum(axis=0)
        curves[f"patch {res.obs_ids[j]} before"] = btr[j]
        bands[f"patch {res.obs_ids[j]} before"] = before.relit_std[j] if before.relit_std is not None else None
    curves[f"patch {res.obs_ids[j]} {tag}"] = tr[j]
    bands[f"patch {res.obs_ids[j]} {tag}"] = None if sd is None else sd[j]
    pic.profiles(res.grid.centres, curves, pics / f"{tag}_profiles.png", bands=bands, log=True,
                 title="time profile (band: +-2 propagated std)")


# ---------------------------------------------------------------------- separate
def _run_separate(args) -> int:
    from . import pictures as pic
    from .records import write_result
    from .separate import separate_capture, separate_nayar

    out, pics = _outputs(args, [args.capture], (".h5",))
    cap = _capture(args.capture)
    sep = separate_capture(cap, threshold=args.threshold)
    ds = {"ids": sep.ids, "direct": sep.direct, "global": sep.global_, "error_bound": sep.error_bound,
          "onset": sep.onset, "direct_transient": sep.direct_transient,
          "global_transient": sep.global_transient}
    summary = {"route": "onsets", **{k: v for k, v in sep.metadata.items() if k != "background_per_bin"}}
    if args.nayar:
        if not cap.is_full:
            raise StircasadiError("--nayar emulates patterns by superposition and needs a full STIR.")
        lay = None
        if args.layout:
            rc = _ints(args.layout, "layout")
            n = len(cap.ill_ids())
            if rc.shape != (2,) or rc[0] * rc[1] != n:
                raise StircasadiError(f"--layout ROWS,COLS must multiply to the {n} illuminated patches; got {args.layout}.")
            lay = np.stack(np.unravel_index(np.arange(n), tuple(rc)), axis=1)
        nay = separate_nayar(cap.stir, cap.grid, cap.ill_ids(), cap.obs_ids(), layout=lay, reference=sep)
        ds.update({"nayar_direct": nay.direct, "nayar_global": nay.global_, "nayar_imbalance": nay.error_bound})
    write_result(out, "separation", ds, summary, grid=cap.grid)
    if _pictures_dir(pics):
        shape = cap.provenance.get("scan_shape")
        if shape is not None and int(np.prod(shape)) == len(sep.ids):
            pic.scan_image(sep.direct, tuple(shape), pics / "direct.png", title="direct (first bounce)", log=True)
            pic.scan_image(np.clip(sep.global_, 0, None), tuple(shape), pics / "global.png",
                           title="global (everything else)", log=True)
        else:
            series = {"direct": sep.direct, "global": sep.global_}
            if args.nayar:
                series.update({"direct (Nayar)": nay.direct, "global (Nayar)": nay.global_})
            pic.bars(sep.ids, series, pics / "direct_global.png", title="direct / global per patch",
                     log=True)
        k = int(np.argmax(sep.direct))
        pic.profiles(cap.grid.centres, {"trace": sep.direct_transient[k] + sep.global_transient[k],
                                        "direct": sep.direct_transient[k]},
                     pics / "profiles.png", log=True, title=f"patch {sep.ids[k]}: direct vs the rest")
    print(f"separate: {len(sep.ids)} patches ({sep.metadata.get('mode')}) -> {out}; direct/global "
          f"median {np.median(sep.direct / np.maximum(np.abs(sep.global_), 1e-300)):.3g}")
    return 0


# ---------------------------------------------------------------------- segment
def _run_segment(args) -> int:
    from . import pictures as pic
    from .records import write_json
    from .segment import SegmentSettings, segment

    out, pics = _outputs(args, [args.estimate], (".json",))
    belief = _belief(args)
    seg = segment(belief, SegmentSettings(level=args.level, max_materials=args.max_materials))
    d = seg.to_json_dict()
    d["verdict"] = belief.verdict
    write_json(out, d)
    if _pictures_dir(pics):
        sc = belief.scene
        lab = np.full(sc.n_patches, np.nan)
        for pid, m in zip(seg.ids, seg.labels):
            lab[belief.index(pid)] = m
        pic.patch_image(sc.positions, sc.normals, sc.areas, lab, sc.camera, pics / "segments.png",
                        title=f"{seg.n_materials} materials (grey: unsegmented)", label="material",
                        ids=belief.ids)
    print(f"segment: {seg.n_materials} materials over {len(seg.ids)} patches, {len(seg.ambiguous)} "
          f"ambiguous, {len(seg.unsegmented)} unsegmented -> {out}")
    return 0


# ---------------------------------------------------------------------- replace
def _run_replace(args) -> int:
    from .records import write_result
    from .render import RenderSettings
    from .replace import make_brdf, replace_material
    from .segment import SegmentSettings, segment

    ins = [x for x in (args.estimate, args.capture, args.segmentation) if x]
    out, pics = _outputs(args, ins, (".h5",))
    belief = _belief(args)
    brdf = make_brdf(args.brdf, args.albedo, args.specular, args.exponent)
    seg = None
    if args.material is not None:
        seg = segment(belief, SegmentSettings(level=args.level))
        if args.segmentation:
            saved = json.loads(Path(args.segmentation).read_text())
            if saved.get("labels") != seg.labels.tolist():
                raise StircasadiError(f"{args.segmentation} does not match this estimate's segmentation "
                                      "at the same level; re-run 'stircasadi segment' on it.")
    cap = _capture(args.capture) if args.capture else None
    rep = replace_material(belief, brdf, ids=_ints(args.ids, "ids"), segmentation=seg, material=args.material,
                           sensor=_sensor_of(cap), source=args.source, camera=args.camera,
                           settings=RenderSettings(bin_width=cap.grid.bin_width if cap is not None else args.bin_width,
                                                   with_std=not args.no_std))
    b, a = rep.before, rep.after
    summary = {"replaced_ids": rep.ids, "brdf": {"kind": brdf.kind, **brdf.params}, **a.metadata}
    write_result(out, "replace", {"stir_before": b.stir, "stir_after": a.stir, "steady_before": b.steady,
                                  "steady_after": a.steady, "steady_std_before": b.steady_std,
                                  "steady_std_after": a.steady_std, "illuminated_ids": a.ill_ids,
                                  "observed_ids": a.obs_ids}, summary, grid=a.grid)
    if _pictures_dir(pics):
        _render_pictures(belief, b, pics, "before", focus=rep.ids[0])
        _render_pictures(belief, a, pics, "after", before=b, focus=rep.ids[0])
    print(f"replace: patches {rep.ids.tolist()} -> {brdf.kind} {brdf.params}; steady state summed "
          f"{b.steady.sum():.4g} -> {a.steady.sum():.4g} -> {out}")
    return 0


# ---------------------------------------------------------------------- deconvolve
def _code(spec: str):
    from .deconvolve import amcw, mls, pulse

    parts = spec.split(":")
    try:
        if parts[0] == "mls":
            return [mls(int(parts[1]))]
        if parts[0] == "pulse":
            return [pulse(int(parts[1]), parts[2] if len(parts) > 2 else "rect")]
        if parts[0] == "amcw":
            lo, hi = (int(x) for x in parts[1].split("-"))
            return amcw(range(lo, hi + 1), int(parts[2]))
    except (IndexError, ValueError):
        pass
    raise StircasadiError(f"--code must be mls:ORDER, pulse:LENGTH[:rect|hann|gauss] or amcw:M1-M2:PERIOD; got {spec!r}.")


def _run_deconvolve(args) -> int:
    from ..capture import Capture
    from . import pictures as pic
    from .deconvolve import DeconvolveSettings, deconvolve, simulate_records
    from .records import read_records, write_json, write_records

    ins = [args.records] if args.records else []
    out, pics = _outputs(args, ins, (".h5",))
    check_output(out.with_suffix(".json"), inputs=ins, what="summary", suffixes=(".json",))
    truth = None
    if args.records is None:
        if not args.emulate:
            raise StircasadiError("deconvolve needs a RECORDS file, or --emulate PROBLEM --code SPEC for a twin.")
        if args.save_records:
            check_output(args.save_records, inputs=[out], what="records", suffixes=(".h5",))
        from ..problem import load_problem
        from ..transport import simulate

        mod = load_problem(args.emulate)
        scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
        tr = simulate(scene, grid, sensor=sensor)
        codes = _code(args.code or "mls:11")
        sig = args.noise * float(np.max(tr.stir))
        rec = simulate_records(tr.stir, codes, sig, np.random.default_rng(args.seed))
        irf = sensor.irf_samples(grid)
        data = {"records": rec, "codes": codes, "grid": grid, "illuminated_ids": tr.ill_ids,
                "observed_ids": tr.obs_ids, "irf": irf, "noise_sigma": None, "legs_included": True}
        truth = tr.stir
        if args.save_records:
            write_records(args.save_records, rec, codes, grid, tr.ill_ids, tr.obs_ids, irf=irf)
    else:
        data = read_records(args.records)
    grid = data["grid"]
    irf = None
    if data["irf"] is not None:
        from ..irf import from_samples
        irf = from_samples(data["irf"], grid.bin_width)
    sigma = args.sigma if args.sigma is not None else data["noise_sigma"]
    d = deconvolve(data["records"], data["codes"], grid.n_bins, sigma=sigma, bin_width=grid.bin_width,
                   irf=irf, settings=DeconvolveSettings(method=args.method))
    cap = Capture(grid=grid, stir=d.h, legs_included=data["legs_included"],
                  illuminated_ids=data["illuminated_ids"], observed_ids=data["observed_ids"],
                  irf=data["irf"], noise={"model": "gaussian", "sigma": float(np.median(d.std))},
                  provenance={"producer": "stircasadi deconvolve", "codes": ",".join(d.metadata["codes"]),
                              "method": args.method})
    cap.write(out)
    summary = {k: v for k, v in d.metadata.items()}
    summary.update({"error_rms_per_bin_median": float(np.median(d.error_rms)),
                    "noise_std_per_bin_median": float(np.median(d.std)),
                    "sigma_median": float(np.median(d.sigma))})
    if truth is not None:
        summary["measured_error_rms_per_bin_median"] = float(np.median(np.sqrt(np.mean((d.h - truth) ** 2, axis=-1))))
    write_json(out.with_suffix(".json"), summary)
    if _pictures_dir(pics):
        i, j = np.unravel_index(np.argmax(d.h.max(axis=-1)), d.h.shape[:2])
        curves = {"recovered": d.h[i, j]}
        if truth is not None:
            curves["impulse STIR (truth)"] = truth[i, j]
        pic.profiles(grid.centres, curves, pics / "deconvolved.png", bands={"recovered": d.error_rms[i, j] * np.ones(grid.n_bins)},
                     title=f"trace ({i}, {j}) from {d.metadata['codes'][0]}... ({len(data['codes'])} code(s))")
    print(f"deconvolve: {len(data['codes'])} code(s), period {d.metadata['period']} -> {out} (+ .json); "
          f"predicted error per bin (median) {summary['error_rms_per_bin_median']:.3g}")
    return 0


# ---------------------------------------------------------------------- registration
def add_parsers(sub) -> None:
    """Register relight, separate, segment, replace and deconvolve on ``sub``."""
    f = argparse.ArgumentDefaultsHelpFormatter
    r = sub.add_parser("relight", formatter_class=f,
                       help="relight a scene: superposition of a measured STIR, or render the estimate "
                            "from a new source/camera with propagated std")
    r.add_argument("capture", nargs="?", default=None, help="Capture HDF5 (its STIR, impulse response, bin width)")
    r.add_argument("--estimate", default=None, help="estimate.json to render from (patches never lit, new source/camera)")
    _common(r, "relit result", ".h5")
    r.add_argument("--weights", default=None, help="comma-separated energy weight per lit patch (default: all 1)")
    r.add_argument("--ids", default=None, help="patch ids the weights belong to (default: every illuminated patch in order)")
    r.add_argument("--delays", default=None, help="emission delay per weight, metres of optical path")
    r.add_argument("--pulse", default=None, help="temporal pulse shape, energy per bin (comma-separated; default an impulse)")
    r.add_argument("--bounces", default=None, help="bounce order of the render (default: what the scene needs; or 'all')")
    _estimate_args(r, render=True)
    r.set_defaults(func=lambda a: _run_relight(_fix_xyz(a)))

    s = sub.add_parser("separate", formatter_class=f, help="direct/global separation of a capture per patch")
    s.add_argument("capture", help="Capture HDF5 (full STIR, or confocal traces)")
    _common(s, "separation result", ".h5")
    s.add_argument("--threshold", type=float, default=0.2, help="fraction of a trace's peak that marks its first return")
    s.add_argument("--nayar", action="store_true", help="also emulate Nayar et al.'s two complementary patterns")
    s.add_argument("--layout", default=None, metavar="ROWS,COLS",
                   help="scan grid of the illuminated patches for the checkerboard (default: alternate ids)")
    s.set_defaults(func=_run_separate)

    g = sub.add_parser("segment", formatter_class=f, help="group the estimate's patches into materials")
    g.add_argument("estimate", help="estimate.json")
    _common(g, "segmentation", ".json")
    g.add_argument("--level", type=float, default=0.01, help="test level of the chi-square tests")
    g.add_argument("--max-materials", type=int, default=None, help="most materials considered")
    _estimate_args(g)
    g.set_defaults(func=_run_segment)

    p = sub.add_parser("replace", formatter_class=f, help="give patches another BRDF and re-render before/after")
    p.add_argument("estimate", help="estimate.json")
    _common(p, "before/after result", ".h5")
    p.add_argument("--ids", default=None, help="patch ids to replace")
    p.add_argument("--material", type=int, default=None, help="replace every patch of this material index instead")
    p.add_argument("--segmentation", default=None, help="segmentation.json the material index refers to (checked)")
    p.add_argument("--level", type=float, default=0.01, help="segmentation test level (with --material)")
    p.add_argument("--brdf", choices=["lambertian", "phong"], required=True, help="the new material's model")
    p.add_argument("--albedo", type=float, default=None, help="diffuse albedo in [0, 1]")
    p.add_argument("--specular", type=float, default=None, help="Phong specular reflectance (albedo + specular <= 1)")
    p.add_argument("--exponent", type=float, default=None, help="Phong exponent >= 0")
    p.add_argument("--capture", default=None, help="Capture whose impulse response and bin width the render uses")
    _estimate_args(p, render=True)
    p.set_defaults(func=lambda a: _run_replace(_fix_xyz(a)))

    d = sub.add_parser("deconvolve", formatter_class=f,
                       help="recover the impulse STIR from coded-illumination records")
    d.add_argument("records", nargs="?", default=None, help="records HDF5 (format stircasadi.records)")
    _common(d, "recovered Capture", ".h5")
    d.add_argument("--method", choices=["gcv", "discrepancy"], default="gcv",
                   help="how the regularisation is chosen (discrepancy needs the noise std)")
    d.add_argument("--sigma", type=float, default=None, help="noise std of the records (default: the file's, else estimated)")
    d.add_argument("--emulate", default=None, metavar="PROBLEM", help="twin: records of PROBLEM's STIR under --code")
    d.add_argument("--code", default=None, help="with --emulate: mls:ORDER, pulse:LENGTH[:shape] or amcw:M1-M2:PERIOD")
    d.add_argument("--noise", type=float, default=1e-3, help="with --emulate: noise std as a fraction of the STIR's peak")
    d.add_argument("--seed", type=int, default=0, help="with --emulate: noise seed")
    d.add_argument("--save-records", default=None, help="with --emulate: also write the records file here")
    d.set_defaults(func=_run_deconvolve)


def _fix_xyz(args):
    args.source = _xyz(args.source, "source")
    args.camera = _xyz(args.camera, "camera")
    return args
