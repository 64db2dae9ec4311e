"""The paper's explicit state-space form x[t+1] = A x[t] + B u[t], y[t] = C x[t] (integer delays).

When to use: to inspect and simulate the seed's formulation on small scenes; it is the baseline
the other methods are measured against (it is slow and large: one state per bin of delay).

Construction: every leg is rounded to n >= 1 whole bins (``delay_mode='integer'``). Each node of
the delay network (``stircasadi.transport.system``; with ``link_level=True`` one node per link
L_ki, the paper's general form factors f_kij) owns a shift register r of length
max(delay of its outgoing terms): r_t[m] = u[t-1-m]. Each illuminated patch owns an input
register fed by B. A writes the node values computed from register taps into each register's
first cell and shifts the rest; C reads the taps the camera sees:

    u_r[t] = sum_S coef * in_p[t - n] + sum_T coef * u_c[t - n],   y_j[t] = sum_O coef * u_c[t - n].

The input is a unit impulse at t = 0 on the aimed patch (the pulse energy phi is in S).
Sample t is the instant t * bin_width; it is binned into the bin that starts there, then
convolved with the sensor's discrete impulse response, exactly as the other methods in
integer-delay mode.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from ..errors import TransportError
from ..progress import progress
from ..timegrid import TimeGrid
from .deposit import bin_integer_samples
from .system import TransportSystem


@dataclass
class StateSpace:
    A: sparse.csr_matrix
    B: sparse.csr_matrix
    C: sparse.csr_matrix
    bin_width: float
    n_states: int

    @property
    def shapes(self) -> dict:
        return {"A": self.A.shape, "B": self.B.shape, "C": self.C.shape,
                "nnz_A": int(self.A.nnz)}


def build_state_space(system: TransportSystem) -> StateSpace:
    """Sparse A, B, C of the shift-register state space of an integer-delay network."""
    if system.delay_mode != "integer":
        raise TransportError("The explicit state space needs integer delays: build the network with "
                             "delay_mode='integer' (legs rounded to whole bins).")
    w = system.bin_width
    def nbins(l):
        return np.rint(l / w).astype(np.int64)
    Sr, Sc, Sv, Sl = system.S
    Tr, Tc, Tv, Tl = system.T
    Or, Oc, Ov, Ol = system.O
    Sn, Tn, On = nbins(Sl), nbins(Tl), nbins(Ol)
    if (len(Sn) and Sn.min() < 1) or (len(Tn) and Tn.min() < 1) or (len(On) and On.min() < 1):
        raise TransportError("Every delay must be at least one bin in the state space.")
    ni, nu, no = system.n_ill, system.n_nodes, system.n_obs
    in_len = np.zeros(ni, np.int64)
    np.maximum.at(in_len, Sc, Sn)
    node_len = np.zeros(nu, np.int64)
    np.maximum.at(node_len, Tc, Tn)
    np.maximum.at(node_len, Oc, On)
    in_off = np.concatenate([[0], np.cumsum(in_len)])
    node_off = in_off[-1] + np.concatenate([[0], np.cumsum(node_len)])
    n_states = int(node_off[-1])
    rows, cols, vals = [], [], []
    # shifts inside every register: cell m takes cell m-1
    for off, lens in ((in_off, in_len), (node_off, node_len)):
        for start, L in zip(off[:-1], lens):
            if L > 1:
                idx = np.arange(start + 1, start + L)
                rows.append(idx); cols.append(idx - 1); vals.append(np.ones(L - 1))
    # node values into the first cell of each node register (only nodes with a register)
    has_reg = node_len[Sr] > 0
    rows.append(node_off[:-1][Sr[has_reg]]); cols.append(in_off[:-1][Sc[has_reg]] + Sn[has_reg] - 1)
    vals.append(Sv[has_reg])
    has_reg = node_len[Tr] > 0
    rows.append(node_off[:-1][Tr[has_reg]]); cols.append(node_off[:-1][Tc[has_reg]] + Tn[has_reg] - 1)
    vals.append(Tv[has_reg])
    A = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(n_states, n_states))
    has_in = in_len > 0
    B = sparse.csr_matrix((np.ones(int(has_in.sum())), (in_off[:-1][has_in], np.flatnonzero(has_in))),
                          shape=(n_states, ni))
    C = sparse.csr_matrix((Ov, (Or, node_off[:-1][Oc] + On - 1)), shape=(no, n_states))
    return StateSpace(A, B, C, w, n_states)


def simulate_state_space(ss: StateSpace, system: TransportSystem, grid: TimeGrid, irf) -> np.ndarray:
    """Run x[t+1] = A x[t] + B u[t] for a unit pulse on each illuminated patch; return the STIR."""
    w = grid.bin_width
    if not grid.is_integer_aligned():
        raise TransportError(f"The state space samples t = n * bin_width; the grid start "
                             f"{grid.start} m must be a whole number of bins ({w} m).")
    s0 = int(round(grid.start / w))
    h, off = irf.discrete(w)
    n_steps = max(s0 + grid.n_bins + off + 1, 1)
    ni, no = system.n_ill, system.n_obs
    samples = np.zeros((n_steps, no, ni))
    X = np.zeros((ss.n_states, ni))
    A, Bm, C = ss.A, ss.B.toarray(), ss.C
    for t in progress(range(n_steps), desc="state space", unit="step"):
        samples[t] = C @ X
        X = A @ X
        if t == 0:
            X += Bm
    return bin_integer_samples(np.transpose(samples, (2, 1, 0)), grid, irf)
