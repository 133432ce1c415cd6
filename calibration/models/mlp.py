"""A small torch MLP (colour change, reference colour and pixel position -> normal), as the
GelSight SDK does, trained deterministically: the learned baseline.

Inputs per pixel: the colour change ``I - I_ref`` and the reference ``I_ref`` of every
pattern-channel (divided by ``input_scale``) and the normalised position ``(u, v)``; output:
the normal's ``(n_x, n_y)`` (bounded, unlike gradients near the rim), with
``n_z = sqrt(1 - n_x^2 - n_y^2)``. Full-batch Adam(W) with a cosine learning-rate decay and an
L1 loss; the seed and ``torch.use_deterministic_algorithms`` make two fits bit-identical.
Optionally an ensemble of ``members`` nets (mean prediction, spread as confidence).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.base import CalibrationModel, ensemble_arrays, ensemble_states, seeded_torch
from calibration.models.nearfield import poly_terms
from calibration.samples import Samples
from pipeline.base.frames import normals_to_gradients

__all__ = ["MLPModel", "FEATURES"]

#: Input features per pixel (besides the position): the colour change and the reference
#: colour; the change alone; the raw colour (what the GelSight SDK feeds, B, G, R).
FEATURES = ("change+reference", "change", "colour")


class MLPModel(CalibrationModel):
    """Position-aware MLP.

    Parameters
    ----------
    hidden : int
        Width of each hidden layer.
    layers : int
        Number of hidden layers.
    epochs : int
        Full-batch Adam steps. 400 at ``lr`` 2e-2 by default: on the shared real frames (CV on
        presses 0-19, detected circles, without rim weighting) 200 steps gave 7.8 deg, 400 7.0,
        800 7.0 and 1600 7.1; a width of 16 or 64, 2 or 4 layers, a learning rate of 1e-2 or
        8000 samples each changed it by at most 0.2 deg, none consistently over the detected
        and label settings (``iristac bench calibration``).
    lr : float
        Peak learning rate (cosine decay to 0).
    seed : int
    max_samples : int
        Training pixels drawn (seeded) from the samples, contact pixels first: full-batch
        steps cost time linear in this.
    input_scale : float
        Camera values are divided by this (255 for 8-bit frames).
    device : str
        Torch device ("cpu", "cuda").
    threads : int or None
        Torch intra-op threads while fitting and predicting (None: leave torch's setting).
    members : int
        Ensemble size: members differ in seed (initial weights and drawn pixels); the
        prediction is their mean and the confidence their agreement.
    weight_decay : float
        AdamW's decoupled weight decay (0: plain Adam).
    features : {"change+reference", "change", "colour"}
        Per-pixel inputs besides the position (:data:`FEATURES`).
    rim_weight : float
        Weight in the loss of a contact pixel at the rim relative to one at the cap's apex,
        ``w = 1 + (rim_weight - 1) rho^2`` (``rho`` = distance over contact radius,
        :attr:`calibration.samples.Samples.radial`); flat pixels weigh 1. 1: all equal. 4 by
        default: the steep rim is where the errors are largest and an L1 fit on mostly gentle
        pixels under-serves it; on the shared real frames (CV on presses 0-19, three seeds)
        4 gave 6.70 deg instead of 7.11 on detected circles and 7.06 instead of 7.52 on hand
        labels; 0.25-0.5 and 8 did worse (``iristac bench calibration``).
    position_degree : int
        Degree of the polynomial in the normalised pixel position fed with ``position``
        (1: ``u, v``; 2 adds ``u^2, uv, v^2``).
    """

    name = "mlp"

    def __init__(self, hidden: int = 32, layers: int = 3, epochs: int = 400, lr: float = 2e-2, seed: int = 0,
                 input_scale: float = 255.0, position: bool = True, max_samples: int = 4000, device: str = "cpu",
                 threads: int | None = 1, members: int = 1, weight_decay: float = 0.0,
                 features: str = "change+reference", rim_weight: float = 4.0, position_degree: int = 1):
        if features not in FEATURES:
            raise ValueError(f"MLPModel: features must be one of {', '.join(FEATURES)}, got {features!r}")
        if int(members) < 1:
            raise ValueError(f"MLPModel: members must be >= 1, got {members}")
        self.hidden, self.layers, self.epochs, self.lr, self.seed = hidden, layers, epochs, lr, seed
        self.input_scale, self.position, self.device = input_scale, position, device
        self.max_samples = max_samples
        self.threads = threads
        self.members, self.weight_decay, self.features = int(members), float(weight_decay), features
        if not rim_weight > 0 or int(position_degree) < 1:
            raise ValueError(f"MLPModel: rim_weight must be > 0 and position_degree >= 1, got {rim_weight}, "
                             f"{position_degree}")
        self.rim_weight, self.position_degree = float(rim_weight), int(position_degree)
        self.nets: list = []
        self.shape: tuple[int, int] | None = None
        self.reference: np.ndarray | None = None

    @property
    def net(self):
        """The first member (the only one unless ``members > 1``)."""
        return self.nets[0] if self.nets else None

    def _features(self, intensities, reference, rows, cols, shape) -> np.ndarray:
        n = len(rows)
        d = (intensities - reference).reshape(n, -1) / self.input_scale
        r = reference.reshape(n, -1) / self.input_scale
        if self.features == "change+reference":
            parts = [d * 4.0, r]
        elif self.features == "change":
            parts = [d * 4.0]
        else:  # "colour": the raw frame, as the GelSight SDK feeds B, G, R, x, y
            parts = [d + r]
        if self.position:
            parts.append(poly_terms(rows, cols, shape, self.position_degree)[:, 1:])
        return np.concatenate(parts, axis=1).astype(np.float32)

    def _draw(self, samples: Samples, seed: int | None = None) -> np.ndarray:
        # Contact pixels carry the information; flat ones only pin the zero. Draw up to half
        # of the budget from each, the rest of the budget going to whichever has more.
        rng = np.random.default_rng(self.seed if seed is None else seed)
        con, flat = np.nonzero(samples.contact)[0], np.nonzero(~samples.contact)[0]
        n_flat = min(len(flat), max(self.max_samples // 4, self.max_samples - len(con)))
        n_con = min(len(con), self.max_samples - n_flat)
        return np.sort(np.concatenate([rng.choice(con, n_con, replace=False), rng.choice(flat, n_flat, replace=False)]))

    def _build(self, n_in: int):
        import torch

        mods: list = []
        width = n_in
        for _ in range(self.layers):
            mods += [torch.nn.Linear(width, self.hidden), torch.nn.SiLU()]
            width = self.hidden
        mods.append(torch.nn.Linear(width, 2))
        return torch.nn.Sequential(*mods).to(self.device)

    def training_set(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every sample's features ``(N, F)``, target ``(n_x, n_y)`` ``(N, 2)`` and loss weight
        ``(N,)`` (``rim_weight`` toward the contact's rim), float32; :meth:`draw` picks the ones a
        net trains on."""
        x = self._features(samples.intensities, samples.reference, samples.rows, samples.cols, samples.shape)
        y = samples.normals[:, :2].astype(np.float32)
        w = np.ones(len(samples), np.float32)
        if self.rim_weight != 1.0 and samples.radial is not None:
            rho2 = np.where(samples.contact, np.clip(samples.radial, 0.0, 1.0) ** 2, 0.0)
            w = (1.0 + (self.rim_weight - 1.0) * rho2).astype(np.float32)
        return x, y, w

    def draw(self, samples: Samples, seed: int) -> np.ndarray:
        """The indices of the samples a net seeded ``seed`` trains on."""
        return self._draw(samples, seed)

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        x_all, y_all, w_all = self.training_set(samples)
        self.shape = samples.shape
        if reference is not None:
            self.reference = np.asarray(reference, dtype=np.float32)
        # Members differ in their seed: initial weights and the drawn training pixels.
        self.nets, losses = [], []
        for i in range(self.members):
            train = self._draw(samples, self.seed + i)
            net, loss = self._train(x_all[train], y_all[train], self.seed + i, w_all[train])
            self.nets.append(net)
            losses.append(loss)
        rep = self._fit_report(samples)
        rep["final_l1_loss"] = float(np.mean(losses))
        rep["members"] = len(self.nets)
        return rep

    def _train(self, x: np.ndarray, y: np.ndarray, seed: int, weights: np.ndarray | None = None):
        import torch

        with seeded_torch(seed, self.threads):
            net = self._build(x.shape[1])
            xt = torch.from_numpy(x).to(self.device)
            yt = torch.from_numpy(y).to(self.device)
            # Per-pixel weights (rim weighting), normalised to mean 1 so the learning rate means the same.
            wt = None if weights is None or np.all(weights == 1) else \
                torch.from_numpy((weights / weights.mean()).astype(np.float32)[:, None]).to(self.device)
            opt = torch.optim.AdamW(net.parameters(), lr=self.lr, weight_decay=self.weight_decay)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(self.epochs, 1))
            loss = torch.zeros(())
            for _ in range(self.epochs):
                opt.zero_grad()
                loss = torch.nn.functional.l1_loss(net(xt), yt) if wt is None else (wt * (net(xt) - yt).abs()).mean()
                loss.backward()
                opt.step()
                sched.step()
        return net.eval(), float(loss.detach())

    confidence_meaning = ("agreement of the ensemble members: exp(-s / 0.05), s the RMS spread of their (n_x, n_y); "
                          "1 for a single member")

    def _predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, ok, spread = self._predict_features(self._features(samples.intensities, samples.reference, samples.rows,
                                                              samples.cols, samples.shape), spread=True)
        return n, ok, np.where(ok, np.exp(-spread / 0.05), 0.0)

    def _predict_features(self, x: np.ndarray, spread: bool = False):
        import torch

        with torch.no_grad(), seeded_torch(self.seed, self.threads):
            xt = torch.from_numpy(x).to(self.device)
            outs = np.stack([net(xt).cpu().numpy().astype(np.float64) for net in self.nets])
        out = outs.mean(axis=0)
        sd = np.sqrt(np.sum(outs.var(axis=0), axis=1))
        r2 = np.sum(out ** 2, axis=1)
        # Outputs outside the unit disc have no normal: shrink them onto a 85-degree tilt.
        s = np.where(r2 > 0.996, np.sqrt(0.996 / np.maximum(r2, 1e-12)), 1.0)
        out = out * s[:, None]
        n = np.concatenate([out, np.sqrt(1.0 - np.sum(out ** 2, axis=1, keepdims=True))], axis=1)
        ok = np.isfinite(n).all(axis=1)
        return (n, ok, sd) if spread else (n, ok)

    def lookup(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients of frames, like :meth:`calibration.models.lut.LookupTable.lookup`.

        Parameters
        ----------
        images : ndarray, shape (N, H, W, C) (single pattern) or (N, P, H, W, C)

        Returns
        -------
        gradients : ndarray, shape (N, H, W, 2); valid : ndarray, shape (N, H, W)
        """
        images = np.asarray(images, dtype=np.float32)
        if images.ndim == 4:
            images = images[:, None]
        if self.reference is None or images.shape[1:] != self.reference.shape:
            raise ValueError(f"MLPModel.lookup: images must be (N, {self.reference.shape}) frames, got {images.shape}")
        maps = self.normal_maps(images)
        gx, gy = normals_to_gradients(maps.normals.astype(np.float64))
        return np.stack([gx, gy], -1).astype(np.float32), maps.mask

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays for calibration.h5 (inverse: :meth:`from_arrays`).

        ``weights/<param>`` (the first member), ``members/<i>/<param>`` (the others),
        ``config = [hidden, layers, position, members, feature index, position degree]``, ``input_scale``,
        ``reference``.
        """
        arrays = ensemble_arrays(self.nets)
        arrays["config"] = np.array([self.hidden, self.layers, int(self.position), len(self.nets),
                                     FEATURES.index(self.features), self.position_degree], dtype=np.int64)
        arrays["input_scale"] = np.asarray(self.input_scale, dtype=np.float64)
        if self.reference is not None:
            arrays["reference"] = self.reference
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], device: str = "cpu") -> "MLPModel":
        """A fitted model from :meth:`to_arrays`' output (files written before ensembles load too)."""

        cfg = [int(v) for v in np.asarray(arrays["config"]).ravel()]
        hidden, layers, position = cfg[:3]
        members = cfg[3] if len(cfg) > 3 else 1
        features = FEATURES[cfg[4]] if len(cfg) > 4 else "change+reference"
        degree = cfg[5] if len(cfg) > 5 else 1
        scale = float(arrays["input_scale"]) if "input_scale" in arrays else 255.0
        model = cls(hidden=hidden, layers=layers, position=bool(position), input_scale=scale, members=members,
                    features=features, device=device, position_degree=degree)
        ref = arrays.get("reference")
        model.reference = None if ref is None else np.asarray(ref, np.float32)
        if model.reference is not None:
            model.shape = tuple(model.reference.shape[1:3])
        for state in ensemble_states(arrays, members):
            first = state[min(k for k in state if k.endswith("weight"))]
            net = model._build(int(first.shape[1]))
            net.load_state_dict(state)
            model.nets.append(net.eval())
        return model
