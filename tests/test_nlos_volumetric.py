"""Volumetric NLOS reconstructions (LCT, f-k, filtered backprojection) against known depths.

Twins: a 16 x 16 confocal wall scan of hidden planes rendered by ``transport.simulate``
(tests/nlos_twins.py); real data: the Stanford 40 cm charts (skipped when the data are absent).
"""
import numpy as np
import pytest

from nlos_twins import confocal_capture, paired_capture, render, surface_patches
from stircasadi.datasets import data_dir
from stircasadi.errors import ReconstructionError
from stircasadi.nlos import VolumeSettings, backprojection, fk, from_capture, lct, plane_fit
from stircasadi.nlos.lct import resampling_operator
from stircasadi.timegrid import TimeGrid


@pytest.fixture(scope="module")
def two_planes():
    """A plane at 0.30 m (left) and a plane at 0.42 m (right), both parallel to the wall."""
    a, ta = surface_patches(lambda x, y: 0.30 + 0 * x, 0.06, 6, rho=0.8)
    b, tb = surface_patches(lambda x, y: 0.42 + 0 * x, 0.06, 6, rho=0.8)
    a = [type(p)((p.centre[0] - 0.12, p.centre[1], p.centre[2]), p.normal, p.area, p.brdf, True) for p in a]
    b = [type(p)((p.centre[0] + 0.12, p.centre[1], p.centre[2]), p.normal, p.area, p.brdf, True) for p in b]
    stir, grid, xyz = render(16, 0.3, a + b, n_bins=220)
    return stir, grid, xyz


@pytest.mark.parametrize("method", [lct, fk, backprojection])
def test_two_depths_recovered_within_a_bin(two_planes, method):
    stir, grid, xyz = two_planes
    rl = from_capture(confocal_capture(stir, grid, xyz, noise_rel=0.01))
    V = method(rl, VolumeSettings(gate_m=0.2))
    m = V.maps()
    # LCT / f-k: one depth bin (path bin / 2) plus 1 mm; filtered backprojection: 1.5 cm (its
    # ellipsoids smear the near plane toward the wall; measured -13 mm on the 0.30 m plane)
    tol = grid.bin_width / 2 + 1e-3 if method is not backprojection else 0.015
    seen = m.albedo > 0.1
    left = seen & (m.x[None, :] < -0.08) & (np.abs(m.y[:, None]) < 0.04)
    right = seen & (m.x[None, :] > 0.08) & (np.abs(m.y[:, None]) < 0.04)
    assert left.sum() >= 2 and right.sum() >= 2
    assert abs(np.median(m.depth[left]) - 0.30) < tol
    assert abs(np.median(m.depth[right]) - 0.42) < tol


def test_lct_float32_matches_float64(two_planes):
    stir, grid, xyz = two_planes
    rl = from_capture(confocal_capture(stir, grid, xyz))
    v32 = lct(rl, VolumeSettings(gate_m=0.2, dtype="float32")).vol
    v64 = lct(rl, VolumeSettings(gate_m=0.2, dtype="float64")).vol
    assert np.max(np.abs(v32 - v64)) < 1e-4 * np.max(v64)


def test_resampling_operator_rows_average_their_subsamples():
    A = resampling_operator(4).toarray()
    # u-bin 0 averages x = 1..4 of tau(ceil(sqrt x)) / sqrt x: x=1 -> t1; x=2,3,4 -> t2
    assert A[0, 0] == pytest.approx(1 / 4)
    assert A[0, 1] == pytest.approx((1 / np.sqrt(2) + 1 / np.sqrt(3) + 1 / 2) / 4)
    assert A.shape == (4, 4) and np.all(A >= 0)


def test_backprojection_non_confocal_pairs(two_planes):
    stir, grid, xyz = two_planes
    cap = paired_capture(stir, grid, xyz, laser_rows=[0, 15, 240, 255, 119, 136])
    rl = from_capture(cap)
    assert not rl.confocal
    V = backprojection(rl, VolumeSettings(gate_m=0.2, n_lateral=16, chunk_bytes=2 ** 20))
    m = V.maps()
    right = (m.albedo > 0.1) & (m.x[None, :] > 0.08) & (np.abs(m.y[:, None]) < 0.04)
    assert right.any() and abs(np.median(m.depth[right]) - 0.42) < 0.01
    with pytest.raises(ReconstructionError, match="confocal"):
        lct(rl)


def test_block_summed_scans_are_accepted(two_planes):
    """``confocal_grid`` judges a scan's evenness on its points' own coordinates. It judged the
    coordinates rounded to multiples of a thousandth of the span, which on the Stanford 64-point
    scans summed in 2 x 2 or 4 x 4 blocks (``subsample_confocal``) alternate by one rounding step
    (50.4 / 51.2 mm on the exit sign's), so LCT and f-k refused them. The returned coordinates are
    still the rounded ones (within half a rounding step of the scan's; see ``confocal_grid``).
    Known answers: the linspace of the scan and the means of its blocks to half a step, the counts
    conserved; two traces on one grid point are refused."""
    from stircasadi.nlos.estimate import subsample_confocal
    from stircasadi.nlos.relay import Relay, confocal_grid

    stir, grid, xyz = two_planes
    rl = from_capture(confocal_capture(stir, grid, xyz, noise_rel=0.01))
    cg = confocal_grid(rl)
    lin = np.linspace(-0.3, 0.3, 16)
    q = 1e-3 * np.ptp(lin)
    assert np.max(np.abs(cg.x - lin)) <= q / 2 + 1e-12 and np.max(np.abs(cg.y - lin)) <= q / 2 + 1e-12
    cg2 = confocal_grid(subsample_confocal(rl, 2))
    for a in (cg2.x, cg2.y):
        assert np.max(np.abs(a - lin.reshape(8, 2).mean(axis=1))) <= q
    assert np.allclose(cg2.data.sum(axis=(0, 1)), cg.data.sum(axis=(0, 1)), rtol=1e-5)
    # the exit sign's grid: 64 points over +-0.4 m, summed in 2 x 2 and 4 x 4 blocks
    frame = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))
    s64 = np.linspace(-0.4, 0.4, 64)
    yy, xx = np.meshgrid(s64, s64, indexing="ij")
    L = np.c_[xx.ravel(), yy.ravel(), np.zeros(64 * 64)]
    nrm = np.tile([0, 0, 1.0], (64 * 64, 1))
    rng = np.random.default_rng(3)
    big = Relay(rng.poisson(2.0, (64 * 64, 8)).astype(float), TimeGrid(0.0, 0.005, 8), L, L.copy(), nrm,
                nrm.copy(), 0.0, 1.0, confocal=True, frame=frame)
    for step in (2, 4):
        cgs = confocal_grid(subsample_confocal(big, step))
        assert len(cgs.x) == 64 // step and cgs.data.sum() == big.traces.sum()
    L2 = L.copy()
    L2[1] = L2[0]
    with pytest.raises(ReconstructionError, match="one trace per scan grid point"):
        confocal_grid(Relay(big.traces, big.grid, L2, L2.copy(), nrm, nrm.copy(), 0.0, 1.0, confocal=True,
                            frame=frame))


def test_missing_wall_points_is_a_clear_error(two_planes):
    stir, grid, xyz = two_planes
    cap = confocal_capture(stir, grid, xyz)
    cap.illuminated_xyz = None
    with pytest.raises(ReconstructionError, match="illuminated_xyz"):
        from_capture(cap)
    with pytest.raises(ReconstructionError, match="bin_factor"):
        VolumeSettings(bin_factor=0).validate()


STANFORD = data_dir() / "otoole2018_confocal"


@pytest.mark.parametrize("name", ["data_resolution_chart_40cm.mat", "data_dot_chart_40cm.mat"])
@pytest.mark.parametrize("method", [lct, fk])
def test_stanford_40cm_charts_depth(name, method):
    """Measured: LCT 0.408 / f-k 0.405 m (resolution chart). The chart's front lies at 0.40 m;
    the volume's brightest voxel sits a few mm behind the onset (IRF and bin)."""
    f = STANFORD / name
    if not f.exists():
        pytest.skip(f"data file absent: {f}")
    from stircasadi.acquisition.importers import read_stanford_lct

    rl = from_capture(read_stanford_lct(f))
    V = method(rl, VolumeSettings(bin_factor=4, diffuse=False, t_max=1.6))
    m = V.maps(z_min=0.2)
    sel = m.albedo > 0.3
    assert sel.sum() >= 3
    assert abs(np.median(m.depth[sel]) - 0.40) < 0.012


def test_diffuse_s_reads_upright_seen_from_the_wall():
    """The release's diffuse "S" (LCT, as ``nlos.pictures.wall_view`` draws it: y up, x to the
    left) against a rasterised bold S fitted to the bright region's box, under the eight turns and
    mirrors of that box. Known answer: the S upright (or turned by 180 degrees, under which an S is
    the same letter). Measured: 0.80 upright and turned, at most 0.61 for the mirrored, transposed
    and quarter-turned ones; the importer's previous axes, (x_j, y_i), gave the transposed S."""
    f = STANFORD / "data_diffuse_s.mat"
    if not f.exists():
        pytest.skip(f"data file absent: {f}")
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextPath

    from stircasadi.acquisition.importers import read_stanford_lct

    m = lct(from_capture(read_stanford_lct(f)), VolumeSettings(bin_factor=4, diffuse=True, t_max=1.4,
                                                               gate_m=0.6)).maps(z_min=0.3)
    assert np.all(np.diff(m.x) > 0) and np.all(np.diff(m.y) > 0)
    pic = np.flipud(np.fliplr(m.albedo))          # seen from the wall, row 0 at the top
    r, c = np.nonzero(pic > 0.5 * np.percentile(pic, 99))
    r0, r1, c0, c1 = np.percentile(r, 2), np.percentile(r, 98), np.percentile(c, 2), np.percentile(c, 98)
    glyph = TextPath((0, 0), "S", size=1, prop=FontProperties(family="DejaVu Sans", weight="bold"))
    ex = glyph.get_extents()
    rr, cc = np.mgrid[0:pic.shape[0], 0:pic.shape[1]]
    p, q = (cc - c0) / (c1 - c0), (rr - r0) / (r1 - r0)      # the letter's box: p right, q down
    boxes = {"upright": (p, q), "turned": (1 - p, 1 - q), "mirrored": (1 - p, q), "flipped": (p, 1 - q),
             "quarter": (q, 1 - p), "three quarters": (1 - q, p), "transposed": (q, p),
             "antitransposed": (1 - q, 1 - p)}

    def corr(P, Q):
        T = glyph.contains_points(np.stack([ex.x0 + P.ravel() * ex.width, ex.y1 - Q.ravel() * ex.height],
                                           1)).reshape(pic.shape).astype(float)
        a, b = pic - pic.mean(), T - T.mean()
        return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))

    score = {k: corr(*pq) for k, pq in boxes.items()}
    right = min(score["upright"], score["turned"])
    wrong = max(v for k, v in score.items() if k not in ("upright", "turned"))
    assert right > 0.7 and right > wrong + 0.1, score


def test_wall_view_draws_x_to_the_left():
    """A map bright at its largest x is drawn on the left: the view from the wall into the hidden
    scene of a right-handed frame whose w points into it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stircasadi.nlos.pictures import wall_view

    x, y = np.linspace(-0.2, 0.2, 5), np.linspace(-0.1, 0.1, 3)
    img = np.zeros((3, 5))
    img[2, 4] = 1.0
    fig, ax = plt.subplots()
    im = wall_view(ax, img, x, y)
    left, right = ax.get_xlim()
    bottom, top = ax.get_ylim()
    assert left == pytest.approx(0.2) and right == pytest.approx(-0.2)
    assert bottom == pytest.approx(-0.1) and top == pytest.approx(0.1)
    # the bright pixel's data position (x = 0.2, y = 0.1) is at the top left of the axes
    px, py = ax.transAxes.inverted().transform(ax.transData.transform((0.2, 0.1)))
    assert px == pytest.approx(0.0) and py == pytest.approx(1.0)
    assert im.get_array()[2, 4] == 1.0
    plt.close(fig)


@pytest.mark.parametrize("name", ["data_resolution_chart_40cm.mat", "data_dot_chart_40cm.mat"])
def test_stanford_40cm_charts_surface_fit(name):
    """The surface fit on the 40 cm charts (16 x 16 traces of 16 ps, each the sum of a 4 x 4 block
    of scan points, modelled with the block's footprint; 12 x 12 nodes from 6 x 6, the default
    sub-samples; the response and background decay measured on the direct return, Lambertian),
    against the charts' rising edges (``nlos.onset``, no model), f-k's depth map (independent
    method) and the response measured on the direct return.

    Measured (resolution / dot, 2026-12-03): the plane through the mask weighted by the nodes'
    precision (``SurfaceResult.plane``) at 0.4062 / 0.4076 m on the scan axis, tilt 1.9 / 2.4 deg
    (the issue asks for within 5 deg); the rising edges 0.4068 / 0.4061 m; f-k's plane 0.4041 /
    0.4048 m, tilt 2.1 / 2.5 deg; chi2/dof 3.91 / 2.94; the fitted core sigma 4.00 / 4.74 mm
    against 4.60 / 4.62 mm measured on the direct return (with 4 x 4 sub-samples per node
    4.47 / 4.90 mm: moment-matched cells wider than the response overstate the spread of a
    patterned chart, so the core comes out narrower). The albedo-weighted plane tilts 2.0 /
    10.2 deg: on the dot chart bright nodes between the rows of dots sit 2.5-7 cm deep with a
    std of 0.8-2.5 mm. Without the footprint (each block one point): chi2/dof 3.98 / 3.04. With step 4d of the
    fit (2026-12-04: one more sub-sample per cell until it changes no lit node by half a std, here
    up to 4 x 4 and a reason) the resolution chart's plane 0.4068 m, tilt 1.7 deg, chi2/dof 2.87,
    core sigma 4.43 mm.

    Why not 0.40 m (the issue's goal, within 2 mm): the charts' own rising edges lie at 0.4068 /
    0.4061 m, and the same reading returns 0.4000 m on a twin of the release at 0.400 m
    (``test_nlos_stanford_twin.py``, where the surface fit returns 0.4005 m). The direct peak
    sits 0.76 / 0.61 mm of path before t = 0 (twin: 0.46 mm), so t = 0 is the wall's peak to a
    fraction of a bin, and the bin-edge convention is right. On the same release's 65 cm charts
    (not in ../shared/data; read from the third-party re-upload, commit 3613ea5, outside the
    repository) the rising edges lie at 0.6523 / 0.6483 m: a constant timing offset between the
    wall's return and the hidden return would shift both distances alike, so the +6 to +7 mm at
    40 cm is where the charts are under the files' own t = 0 (their stated distance is nominal),
    not a convention of the fit. Asserting 0.40 +- 2 mm would need an offset the data do not
    support; the fit is asserted within 2 mm of the rising edges instead."""
    f = STANFORD / name
    if not f.exists():
        pytest.skip(f"data file absent: {f}")
    from stircasadi.acquisition.importers import read_stanford_lct
    from stircasadi.nlos import estimate_capture

    cap = read_stanford_lct(f)
    est = estimate_capture(cap, method="surface", bin_factor=4, diffuse=False, t_max=1.6, gate_m=0.72,
                           wall_step=4, n_nodes=12, levels=2, max_iter=12)
    s = est.surface
    assert s.response == "gaussian" and len(s.extras["slow_tails"]) == 2
    sig_direct = s.extras["response_start"]["sigma"]
    assert abs(sig_direct - 0.0046) < 0.1 * 0.0046              # FWHM ~57 ps with its tails
    assert abs(s.sigma_irf - sig_direct) < 0.2 * sig_direct
    z0, tilt = s.plane()
    m = fk(from_capture(cap), VolumeSettings(bin_factor=4, diffuse=False, t_max=1.6)).maps(z_min=0.2)
    sel = m.albedo > 0.3
    z_fk, tilt_fk = plane_fit(m.points()[sel], m.albedo[sel])
    assert s.mask.sum() >= 20 and s.chi2_dof < 6
    assert 0.400 <= z0 < 0.413 and abs(z0 - z_fk) < 0.008
    assert tilt < 5.0 and tilt_fk < 4.0
    from stircasadi.nlos.onset import onset_depths
    edge = onset_depths(from_capture(cap), 0.72, 1.0)
    assert 0.405 < edge.median < 0.408 and abs(edge.direct_peak) < cap.grid.bin_width
    assert abs(z0 - edge.median) < 0.002


def test_plane_fit_closed_form_with_outliers():
    """A plane z = 0.4 + 0.1 x (tilt atan(0.1) = 5.71 deg) with 10 % of points 5 cm off it: the
    robust fit returns the plane's depth on the axis and its tilt."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.2, 0.2, (300, 2))
    z = 0.4 + 0.1 * xy[:, 0] + rng.normal(0, 1e-4, 300)
    z[:30] += 0.05
    d, tilt = plane_fit(np.c_[xy, z], rng.uniform(0.5, 1.0, 300))
    assert abs(d - 0.4) < 1e-4 and abs(tilt - np.degrees(np.arctan(0.1))) < 0.05
    with pytest.raises(ValueError, match="plane_fit needs"):
        plane_fit(np.zeros((2, 3)), np.ones(2))
