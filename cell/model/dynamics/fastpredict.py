"""Single-sample serving: XGBoost trees compiled into flat numpy arrays, physics through RNEA, causal features.

Stock `Booster.inplace_predict` spends most of a one-row call in set-up (hundreds of microseconds);
walking all trees of all joints level by level as a handful of numpy gathers costs tens.  Every tree
is padded to a complete binary tree of the forest's depth (a leaf above the last level is copied to
all its descendants), so one step per level moves every tree at once.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import xgboost as xgb

from cell.model.dynamics.features import DerivedOne, Group, WindowBuffer, derived_layout
from cell.model.dynamics.learned import PHYSICS_PART, Forest, LearnedModel
from cell.model.dynamics.nets import NetLearner
from cell.model.dynamics.netserve import NetServe
from cell.sensing.derivatives import CausalDerivatives, FilterConfig


def _base_score(model_json: dict) -> float:
    raw = model_json["learner"]["learner_model_param"]["base_score"]
    values = json.loads(raw) if raw.startswith("[") else [float(raw)]
    if len(values) != 1:
        raise ValueError("only single-target boosters can be compiled")
    return float(values[0])


@dataclass
class _Tree:
    left: list[int]
    right: list[int]
    feature: list[int]
    cond: list[float]


def _depth(t: _Tree, node: int = 0) -> int:
    if t.left[node] == -1:
        return 0
    return 1 + max(_depth(t, t.left[node]), _depth(t, t.right[node]))


def _walk_arrays(T: int, D: int) -> tuple[np.ndarray, np.ndarray]:
    """(child, root) of T complete trees of depth D laid out one after another: `child[p]` is the flat position
    of p's left child, in the internal arrays for all levels but the last, in the leaf array for the last."""
    n_int, n_leaf = 2**D - 1, 2**D
    heap = np.arange(n_int)
    child_local = 2 * heap + 1
    last = child_local >= n_int
    child = np.where(last, child_local - n_int, child_local)
    base_int = (np.arange(T) * n_int)[:, None]
    base_leaf = (np.arange(T) * n_leaf)[:, None]
    return (np.where(last[None, :], base_leaf + child[None, :], base_int + child[None, :]).reshape(-1),
            (np.arange(T) * n_int).astype(np.int64))


@dataclass
class _Subset:
    """Some trees of a `FlatForest` (their indices) with arrays of their own for a walk."""

    trees: np.ndarray
    feat: np.ndarray
    thr: np.ndarray
    child: np.ndarray
    root: np.ndarray
    leaf: np.ndarray


class FlatForest:
    """All trees of several single-output boosters as flat arrays; `predict(x)` for one feature row.

    `x` holds every booster's features; `feature_maps[i][f]` is where booster i's feature f sits in
    it (an int offset means a contiguous block).  Inputs must be finite (the missing-value branch is
    not compiled).
    """

    def __init__(self, boosters: list[xgb.Booster], feature_maps: Sequence[np.ndarray | int]) -> None:
        trees: list[_Tree] = []
        owner: list[int] = []
        self.base_score = np.zeros(len(boosters))
        for i, (bst, fmap) in enumerate(zip(boosters, feature_maps, strict=True)):
            mj = json.loads(bst.save_raw("json"))
            self.base_score[i] = _base_score(mj)
            n_feat = int(mj["learner"]["learner_model_param"]["num_feature"])
            where = np.arange(n_feat) + fmap if isinstance(fmap, int) else np.asarray(fmap, np.int64)
            for t in mj["learner"]["gradient_booster"]["model"]["trees"]:
                trees.append(_Tree(t["left_children"], t["right_children"],
                                   [int(where[f]) for f in t["split_indices"]], t["split_conditions"]))
                owner.append(i)
        self.outputs = len(boosters)
        self.n_trees = len(trees)
        depth = max((_depth(t) for t in trees), default=0)
        self.depth = D = max(depth, 1)
        n_int, n_leaf = 2**D - 1, 2**D
        T = len(trees)
        feat = np.zeros((T, n_int), np.int64)
        thr = np.full((T, n_int), np.inf, np.float32)  # padded nodes: x >= inf is False, go left
        leaf = np.zeros((T, n_leaf), np.float64)
        for ti, t in enumerate(trees):
            stack = [(0, 0, 0)]  # (xgboost node, heap position, depth)
            while stack:
                node, h, d = stack.pop()
                if t.left[node] == -1:  # leaf: copy its value to every heap leaf below h
                    span = 2 ** (D - d)
                    first = (h + 1) * span - 1 - n_int  # leftmost heap descendant of h, D - d levels down
                    leaf[ti, first:first + span] = t.cond[node]
                    continue
                feat[ti, h] = t.feature[node]
                thr[ti, h] = np.float32(t.cond[node])
                stack.append((t.left[node], 2 * h + 1, d + 1))
                stack.append((t.right[node], 2 * h + 2, d + 1))
        # Flat arrays; `child[p]` is the flat position of p's left child: in the internal arrays for
        # all levels but the last, in the leaf array for the last internal level.
        self.feat = feat.reshape(-1)
        self.thr = thr.reshape(-1)
        self.leaf = leaf.reshape(-1)
        self.child, self.root = _walk_arrays(T, D)
        owner_arr = np.asarray(owner, np.int64)
        order = np.argsort(owner_arr, kind="stable")
        if not np.array_equal(order, np.arange(T)):
            raise AssertionError("trees must be grouped by booster")
        counts = np.bincount(owner_arr, minlength=self.outputs)
        self.segments = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self._empty = counts == 0
        # Work buffers: predict() allocates nothing per level.
        self._p = np.empty(T, np.int64)
        self._f = np.empty(T, np.int64)
        self._xv = np.empty(T, np.float32)
        self._tv = np.empty(T, np.float32)
        self._go = np.empty(T, bool)
        self._c = np.empty(T, np.int64)
        self._v = np.empty(T, np.float64)
        # Shallow forests: evaluate every split of every tree at once (two calls), then only look
        # the decisions up level by level; deep ones: gather the splits on the path level by level.
        self.all_splits = D <= 4

    def subset(self, columns: np.ndarray | Sequence[int]) -> _Subset:
        """The trees that split on any of `columns`, for `predict_changed`."""
        T, n_int, n_leaf = self.n_trees, 2**self.depth - 1, 2**self.depth
        feat, thr = self.feat.reshape(T, n_int), self.thr.reshape(T, n_int)
        trees = np.flatnonzero((np.isin(feat, np.asarray(columns)) & np.isfinite(thr)).any(axis=1))
        child, root = _walk_arrays(len(trees), self.depth)
        return _Subset(trees, feat[trees].reshape(-1), thr[trees].reshape(-1), child, root,
                       self.leaf.reshape(T, n_leaf)[trees].reshape(-1))

    def leaves(self) -> np.ndarray:
        """Every tree's leaf value in the last `predict` (a copy)."""
        return self._v.copy()

    def predict_changed(self, x: np.ndarray, sub: _Subset, base_leaves: np.ndarray) -> np.ndarray:
        """`predict(x)` for a row that differs from the one `base_leaves` (`leaves()`) came from in the subset's
        columns alone: only the trees that split on them walk again, and the sums are the same, bit for bit
        (every tree's leaf in one array, summed as `predict` sums them)."""
        if not self.all_splits or not self.n_trees:
            return self.predict(x)
        go = x[sub.feat] >= sub.thr
        p = sub.root
        for _ in range(self.depth):
            p = sub.child[p] + go[p]
        v = base_leaves.copy()
        v[sub.trees] = sub.leaf[p]
        out = np.add.reduceat(v, self.segments)
        out[self._empty] = 0.0
        return out + self.base_score

    def predict(self, x: np.ndarray) -> np.ndarray:
        """One row (float32 features) -> (outputs,) predictions."""
        p, f, xv, tv, go, c = self._p, self._f, self._xv, self._tv, self._go, self._c
        p[:] = self.root
        if self.all_splits:
            goall = x[self.feat] >= self.thr
            for _ in range(self.depth):
                p = self.child[p] + goall[p]
        else:
            for _ in range(self.depth):
                np.take(self.feat, p, out=f)
                np.take(x, f, out=xv)
                np.take(self.thr, p, out=tv)
                np.greater_equal(xv, tv, out=go)
                np.take(self.child, p, out=c)
                np.add(c, go, out=p)
        np.take(self.leaf, p, out=self._v)
        out = np.add.reduceat(self._v, self.segments) if self.n_trees else np.zeros(self.outputs)
        out[self._empty] = 0.0
        return out + self.base_score


class FastPredictor:
    """The served model: one sample in, joint torques out, identical to `LearnedModel.predict`.

    `predict_one(q, dq, ddq)` keeps the feature window itself; `step(q, dq)` also runs the causal
    derivative pipeline (`CausalDerivatives`), as the controller does every period.  With
    `stock=True` the trees are evaluated by XGBoost's own `inplace_predict`, one row per booster
    (the benchmark's reference: same features, same physics, only the tree evaluation differs).
    """

    def __init__(self, model: LearnedModel, dt: float, filter_cfg: FilterConfig | None = None,
                 stock: bool = False) -> None:
        self.model = model
        self.kind = model.kind
        self.part = PHYSICS_PART[model.kind]
        self.n = model.forest.n
        self.p2 = model.physics
        # Trust and uncertainty (cell/model/dynamics/uncertainty.py): `coverage` blends the learned part (H1),
        # `trust_model` is any hybrid's, for `last_sigma`.
        self.trust_model = model.coverage if model.kind != "D" else None
        # (a model whose trust is 1 everywhere has nothing to blend: no per-sample work for it)
        self.coverage = (self.trust_model if self.trust_model is not None and self.trust_model.blend
                         and self.trust_model.gates else None)
        self._last_dq = np.zeros(self.n)
        self._last_w = np.ones(self.n)
        self.stock = stock
        groups: list[Group] = model.forest.groups
        self.spec = model.forest.spec
        self.window = WindowBuffer(groups, self.n)
        # x = [window features of every group | the derived-input vector E]
        total_window = sum(g.window_width for g in groups)
        n_extra = len(derived_layout(self.spec, self.n))
        boosters: list[xgb.Booster] = []
        maps: list[np.ndarray | int] = []
        outputs: list[int] = []
        self._slices: list[tuple[np.ndarray, list[int]]] = []
        w_off = 0
        for g in groups:
            fmap = np.concatenate([np.arange(w_off, w_off + g.window_width),
                                   total_window + np.asarray(g.extra, np.int64)]).astype(np.int64)
            self._slices.append((fmap, list(g.outputs)))
            for j in g.outputs:
                if isinstance(model.forest, Forest):
                    boosters.append(model.forest.boosters[j])
                maps.append(fmap)
                outputs.append(j)
            w_off += g.window_width
        self.outputs = np.asarray(outputs, np.int64)
        # A DNN/LSTM part is served by its numpy forward pass; its "stock" reference is the batch path.
        self.forest: FlatForest | NetServe = (
            NetServe(model.forest, [f for f, _ in self._slices]) if isinstance(model.forest, NetLearner)
            else FlatForest(boosters, maps))
        self._stock: dict[int, xgb.Booster] = {}
        if stock and not isinstance(model.forest, Forest):
            self.stock = False
        elif stock and isinstance(model.forest, Forest):
            # Stock reference: copies set to one thread, XGBoost's fastest setting for a single row.
            for j, bst in model.forest.boosters.items():
                copy = xgb.Booster(model_file=bytearray(bst.save_raw()))
                copy.set_param({"nthread": 1})
                self._stock[j] = copy
        self.derivs = CausalDerivatives(self.n, dt, filter_cfg)
        self._x = np.empty(total_window + n_extra, np.float32)
        self._nw = total_window
        self._has_extra = n_extra > 0
        self._derived = DerivedOne(self.spec, self.n)

    def reset(self) -> None:
        self.window.reset()
        self.derivs.reset()

    def predict_one(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        x = self._x
        x[:self._nw] = self.window.push(q, dq, ddq)
        load = None
        if self.part == "none":
            tau = np.full(self.n, np.nan)
        else:
            assert self.p2 is not None
            if self.part == "losses":
                tau = self.p2.losses(q, dq, ddq)
                load = tau
            else:
                load = self.p2.rigid_one(q, dq, ddq)
                tau = load + self.p2.losses(q, dq, ddq) if self.part == "full" else load.copy()
        if self._has_extra:
            x[self._nw:] = self._derived(q, dq, load)
        if self.stock:
            learned = np.empty(len(self.outputs))
            k = 0
            for fmap, outs in self._slices:
                row = x[fmap][None, :]
                for j in outs:
                    learned[k] = self._stock[j].inplace_predict(row)[0]
                    k += 1
        else:
            learned = self.forest.predict(x)
        if self.part == "none":
            tau[self.outputs] = learned
        else:
            if self.trust_model is not None:
                self._last_dq = dq
                if self.trust_model.gates:
                    self._last_w = self.trust_model.weight_one(q, dq, ddq)
                if self.coverage is not None:
                    learned = learned * self._last_w[self.outputs]
            tau[self.outputs] += learned
        return tau

    def last_sigma(self) -> np.ndarray:
        """One-sigma uncertainty [N·m] of the last `predict_one` (NaN without a coverage model)."""
        if self.trust_model is None:
            return np.full(self.n, np.nan)
        return self.trust_model.sigma(self._last_dq, self._last_w)

    def step(self, q: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        v, a = self.derivs.step(q, dq)
        return self.predict_one(np.asarray(q, float), v, a)
