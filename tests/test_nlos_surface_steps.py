"""Two surfaces side by side at different depths (step 4a of ``nlos/surface/fit.py``,
``steps.py``): a labelled grid's difference operators never cross a label's border, and the
labels are drawn only where two lit parts have a depth step between them."""
import numpy as np
import pytest

from stircasadi.errors import ReconstructionError
from stircasadi.nlos.surface.grid import DepthGrid
from stircasadi.nlos.surface.steps import MIN_PART, step_labels

FRAME = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))


def _ops(grid):
    Gx, Gy = grid.gradient_ops()
    Dxx, Dyy, Dxy = grid.curvature_ops()
    return {"Gx": Gx, "Gy": Gy, "Dxx": Dxx, "Dyy": Dyy, "Dxy": Dxy, "Lap": grid.laplacian()}


def test_one_label_everywhere_gives_the_plain_operators():
    """Every node of one label: the same sparse operators as the unlabelled grid, entry for entry."""
    g = DepthGrid(np.linspace(-0.2, 0.2, 7), np.linspace(-0.1, 0.15, 6), FRAME)
    plain, one = _ops(g), _ops(DepthGrid(g.x, g.y, FRAME, labels=np.zeros(g.n, int)))
    for k in plain:
        assert abs(plain[k] - one[k]).max() == 0.0, k


def test_two_labels_give_each_plane_its_own_exact_slope_and_no_coupling():
    """A 8 x 6 grid split between columns 3 and 4 (labels 0 | 1), each side a different plane
    (depths 0.37 and 0.48, slopes (0.2, -0.1) and (-0.3, 0.25)) with a quadratic term on the
    right: the gradient operators return each side's own slope at every node (central inside,
    second-order one-sided at the border, both exact for a parabola), the curvature operators
    each side's own second derivatives, the Laplacian is zero on a plane away from the Neumann
    border, and no operator has an entry joining two nodes of different labels. The plain grid's
    operators at the nodes beside the border mix the two depths (slope ~1.4 m/m there)."""
    x, y = np.linspace(-0.15, 0.15, 8), np.linspace(-0.1, 0.1, 6)
    xx, yy = np.meshgrid(x, y)
    lab = (xx > 0).astype(int)
    left = 0.37 + 0.2 * xx - 0.1 * yy
    right = 0.48 - 0.3 * xx + 0.25 * yy + 0.7 * xx ** 2
    z = np.where(lab == 0, left, right).ravel()
    g = DepthGrid(x, y, FRAME, labels=lab.ravel())
    o = _ops(g)
    gx_true = np.where(lab == 0, 0.2, -0.3 + 1.4 * xx).ravel()
    gy_true = np.where(lab == 0, -0.1, 0.25).ravel()
    assert np.allclose(o["Gx"] @ z, gx_true, atol=1e-12)
    assert np.allclose(o["Gy"] @ z, gy_true, atol=1e-12)
    assert np.allclose(o["Dxx"] @ z, np.where(lab == 0, 0.0, 1.4).ravel(), atol=1e-9)
    assert np.allclose(o["Dyy"] @ z, 0.0, atol=1e-9)
    assert np.allclose(o["Dxy"] @ z, 0.0, atol=1e-9)
    inner = np.zeros_like(lab, bool)
    inner[1:-1, 1:3] = True                               # the left plane, off every run's end
    assert np.allclose((o["Lap"] @ z)[inner.ravel()], 0.0, atol=1e-12)
    L = lab.ravel()
    for k, A in o.items():
        A = A.tocoo()
        assert not np.any(L[A.row] != L[A.col]), k
    plain = DepthGrid(x, y, FRAME).gradient_ops()[0] @ z
    assert abs(plain[2 * 8 + 3]) > 1.0 and abs(plain[2 * 8 + 4]) > 1.0


def _parts(depth_right, gap_cols=1, speck=False):
    """A 10 x 10 albedo map with two lit bars (rows 2-7): columns 1-3 at 0.37 m and, after
    ``gap_cols`` dark columns, three columns at ``depth_right``; the dark nodes at 0.42 m."""
    rho = np.zeros((10, 10))
    z = np.full((10, 10), 0.42)
    rho[2:8, 1:4], z[2:8, 1:4] = 0.6, 0.37
    c = 4 + gap_cols
    rho[2:8, c:c + 3], z[2:8, c:c + 3] = 0.5, depth_right
    if speck:
        rho[0, 9], z[0, 9] = 0.6, 0.2
    return rho, z


def test_labels_split_two_lit_parts_at_a_depth_step_and_nothing_else():
    """Two bars 11 cm apart in depth with one dark column between them (a step of slope 1.45
    over two 3.8 cm nodes): every node takes its nearest bar's label (the bars whole, the grid
    split at the gap's middle); the same with the gap's column lit at a depth between the bars'
    (cells both edges cut: a strip of its own, linked to neither bar, dim: 1.8 of summed albedo
    against the bars' 10.8 and 9). The same bars at one
    depth, or at slope 0.6 (one plane tilted 31 deg could hold them), the gap lit at the bars'
    depth (one part), or a lit speck of fewer than MIN_PART nodes at another depth beside one
    bar: no labels."""
    hx = hy = 0.038
    rho, z = _parts(0.48)
    lab = step_labels((10, 10), z.ravel(), rho.ravel(), hx, hy)
    assert lab is not None
    lab = lab.reshape(10, 10)
    assert len(np.unique(lab[2:8, 1:4])) == 1 and len(np.unique(lab[2:8, 5:8])) == 1
    assert lab[4, 2] != lab[4, 6]
    assert np.all(lab[:, :4] == lab[4, 2]) and np.all(lab[:, 5:] == lab[4, 6])
    rho, z = _parts(0.37)
    assert step_labels((10, 10), z.ravel(), rho.ravel(), hx, hy) is None
    rho, z = _parts(0.37 + 0.6 * 2 * hx)
    assert step_labels((10, 10), z.ravel(), rho.ravel(), hx, hy) is None
    rho, z = _parts(0.37)
    rho[2:8, 4], z[2:8, 4] = 0.6, 0.37
    assert step_labels((10, 10), z.ravel(), rho.ravel(), hx, hy) is None    # one part
    rho, z = _parts(0.48)
    rho[2:8, 4], z[2:8, 4] = 0.3, 0.425       # the gap lit, between the two depths: still split
    lab2 = step_labels((10, 10), z.ravel(), rho.ravel(), hx, hy)
    assert lab2 is not None and np.array_equal(lab2.reshape(10, 10)[:, [0, 3, 5, 9]], lab[:, [0, 3, 5, 9]])
    rho, z = _parts(0.37)
    rho[2:8, 5:8] = 0.0
    rho[2, 5:5 + MIN_PART - 1], z[2, 5:5 + MIN_PART - 1] = 0.6, 0.48       # a speck beside a bar
    assert step_labels((10, 10), z.ravel(), rho.ravel(), hx, hy) is None


def test_a_labelled_grid_keeps_its_labels_through_replace_and_resample():
    """The labelled grid is a dataclass field: ``dataclasses.replace`` keeps the nodes and frame
    and carries the labels; a resample of a map onto it is unchanged by them; labels of the wrong
    length or not integers are refused with what is allowed."""
    from dataclasses import replace
    g = DepthGrid(np.linspace(-0.1, 0.1, 5), np.linspace(-0.1, 0.1, 5), FRAME)
    gl = replace(g, labels=np.arange(25) % 2)
    assert gl.shape == g.shape and np.array_equal(gl.labels, np.arange(25) % 2)
    f = np.linspace(0.3, 0.5, 25)
    assert np.array_equal(g.resample(f, gl), g.resample(f, g))
    with pytest.raises(ReconstructionError, match="25 integers"):
        DepthGrid(g.x, g.y, FRAME, labels=np.zeros(7, int))
    with pytest.raises(ReconstructionError, match="25 integers"):
        DepthGrid(g.x, g.y, FRAME, labels=np.zeros(25))
