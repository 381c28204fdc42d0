"""Single-sample serving of the DNN/LSTM learners: every group's network fused into one block-diagonal network."""

from __future__ import annotations

import numpy as np

from cell.model.dynamics.nets import NetLearner


def _block(blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]], rows: int, cols: int) -> np.ndarray:
    """A (rows, cols) float32 matrix of zeros with each (row indices, column indices, values) block set."""
    out = np.zeros((rows, cols), np.float32)
    for r, c, v in blocks:
        out[np.ix_(r, c)] = v
    return out


class NetServe:
    """The networks on one feature row: `predict(x)` like `FlatForest.predict`, `feature_maps[i]` the
    positions of group i's features in x.

    A numpy call costs about a microsecond whatever its size, so the groups' networks run as one: their
    weights are laid out block-diagonally (zeros between groups), and an LSTM's input projection of all
    window steps is one product before the recurrence; the LSTM's gates are reordered (i, f, o | g) so
    the three sigmoids are one slice.  Same maths as `NetLearner.predict`, float32.
    """

    def __init__(self, learner: NetLearner, feature_maps: list[np.ndarray]) -> None:
        self.depth = 0
        self.n_trees = 0
        p = learner.params
        self.lstm = p.learner == "lstm"
        self.act = np.tanh if p.activation == "tanh" else (lambda v: np.maximum(v, 0))
        groups, nets = learner.groups, [learner.nets[gi] for gi in range(len(learner.groups))]
        self.outputs = sum(len(g.outputs) for g in groups)
        # z = standardised features of all groups, concatenated: z = (x[idx] - mean) * inv
        self.idx = np.concatenate([np.asarray(f, np.int64) for f in feature_maps])
        self.mean = np.concatenate([n.x_mean for n in nets]).astype(np.float32)
        self.inv = (1.0 / np.concatenate([n.x_scale for n in nets])).astype(np.float32)
        self.y_mean = np.concatenate([n.y_mean for n in nets]).astype(np.float32)
        self.y_scale = np.concatenate([n.y_scale for n in nets]).astype(np.float32)
        z_off = np.cumsum([0] + [g.width for g in groups])
        o_off = np.cumsum([0] + [len(g.outputs) for g in groups])
        dense_in: list[np.ndarray] = []  # per group: positions of its first dense layer's inputs in `first`
        if self.lstm:
            W = groups[0].window
            widths = [len(g.base) for g in groups]
            Hs = [n.weights["Wh"].shape[0] for n in nets]
            H = sum(Hs)
            h_off = np.cumsum([0] + Hs)
            # the sequence, oldest step first: seq[t] = z at each group's columns of step W-1-t (newest first in z)
            self.seq_idx = np.stack([np.concatenate([z_off[k] + (W - 1 - t) * w + np.arange(w)
                                                     for k, w in enumerate(widths)]) for t in range(W)])
            w_off = np.cumsum([0] + widths)
            order = (0, 1, 3, 2)  # flax/Keras gate order i, f, g, o -> i, f, o, g
            wi, wh, bb = [], [], []
            for k, n in enumerate(nets):
                hk = Hs[k]
                cols = np.concatenate([gate * H + h_off[k] + np.arange(hk) for gate in range(4)])
                src = np.concatenate([order[gate] * hk + np.arange(hk) for gate in range(4)])
                wi.append((w_off[k] + np.arange(widths[k]), cols, n.weights["Wi"][:, src]))
                wh.append((h_off[k] + np.arange(hk), cols, n.weights["Wh"][:, src]))
                bb.append((np.array([0]), cols, n.weights["b"][src][None, :]))
            self.Wi = _block(wi, int(w_off[-1]), 4 * H)
            self.Wh = _block(wh, H, 4 * H)
            self.b = _block(bb, 1, 4 * H)[0]
            self.H = H
            # the first dense layer sees [h of every group | every group's derived inputs (z)]
            self.extra_idx = np.concatenate([z_off[k] + W * widths[k] + np.arange(g.width - W * widths[k])
                                             for k, g in enumerate(groups)])
            e_off = H + np.cumsum([0] + [g.width - W * widths[k] for k, g in enumerate(groups)])
            dense_in = [np.concatenate([h_off[k] + np.arange(Hs[k]), e_off[k] + np.arange(e_off[k + 1] - e_off[k])])
                        for k in range(len(groups))]
            first, n_in = 1, int(e_off[-1])
        else:
            dense_in = [z_off[k] + np.arange(g.width) for k, g in enumerate(groups)]
            first, n_in = 0, int(z_off[-1])
        self.layers: list[tuple[np.ndarray, np.ndarray]] = []
        cur = dense_in
        for layer in range(first, p.layers):
            sizes = [n.weights[f"W{layer}"].shape[1] for n in nets]
            off = np.cumsum([0] + sizes)
            blocks = [(cur[k], off[k] + np.arange(sizes[k]), n.weights[f"W{layer}"]) for k, n in enumerate(nets)]
            bias = np.concatenate([n.weights[f"b{layer}"] for n in nets]).astype(np.float32)
            self.layers.append((_block(blocks, n_in, int(off[-1])), bias))
            cur = [off[k] + np.arange(sizes[k]) for k in range(len(nets))]
            n_in = int(off[-1])
        blocks = [(cur[k], o_off[k] + np.arange(len(g.outputs)), nets[k].weights["Wout"]) for k, g in enumerate(groups)]
        self.Wout = _block(blocks, n_in, int(o_off[-1]))
        self.bout = np.concatenate([n.weights["bout"] for n in nets]).astype(np.float32)

    def predict(self, x: np.ndarray) -> np.ndarray:
        z = (x[self.idx] - self.mean) * self.inv
        if self.lstm:
            H = self.H
            xin = z[self.seq_idx] @ self.Wi + self.b  # (W, 4H): every step's input projection at once
            h = np.zeros(H, np.float32)
            c = np.zeros(H, np.float32)
            for t in range(xin.shape[0]):
                a = xin[t] + h @ self.Wh
                s = 0.5 * np.tanh(0.5 * a[:3 * H]) + 0.5
                c = s[H:2 * H] * c + s[:H] * np.tanh(a[3 * H:])
                h = s[2 * H:] * np.tanh(c)
            v = np.concatenate([h, z[self.extra_idx]])
        else:
            v = z
        for Wk, bk in self.layers:
            v = self.act(v @ Wk + bk)
        out: np.ndarray = ((v @ self.Wout + self.bout) * self.y_scale + self.y_mean).astype(np.float64)
        return out
