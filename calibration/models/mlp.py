"""A small torch MLP (colour change, reference colour and pixel position -> normal), as the
GelSight SDK does, trained deterministically: the learned baseline.

Inputs per pixel: the colour change ``I - I_ref`` and the reference ``I_ref`` of every
pattern-channel (divided by ``input_scale``) and the normalised position ``(u, v)``; output:
the normal's ``(n_x, n_y)`` (bounded, unlike gradients near the rim), with
``n_z = sqrt(1 - n_x^2 - n_y^2)``. Full-batch Adam with a cosine learning-rate decay and an
L1 loss; the seed and ``torch.use_deterministic_algorithms`` make two fits bit-identical.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np

from calibration.models.base import CalibrationModel
from calibration.models.nearfield import poly_terms
from calibration.samples import Samples
from pipeline.base.frames import normals_to_gradients

__all__ = ["MLPModel"]


@contextlib.contextmanager
def _deterministic(seed: int, threads: int | None = 1):
    import torch

    from pipeline.base.threads import limit_threads

    was = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    # A net this small gains nothing from intra-op threads, and on a loaded 2-core machine
    # the spinning workers cost 30x (measured: 150 steps of 2000 samples, 17 s with 2 threads,
    # 0.5 s with 1).
    try:
        with limit_threads(torch=int(threads) if threads else None):
            torch.manual_seed(seed)
            yield
    finally:
        torch.use_deterministic_algorithms(was)


class MLPModel(CalibrationModel):
    """Position-aware MLP.

    Parameters
    ----------
    hidden : int
        Width of each hidden layer.
    layers : int
        Number of hidden layers.
    epochs : int
        Full-batch Adam steps.
    lr : float
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
    """

    name = "mlp"

    def __init__(self, hidden: int = 32, layers: int = 3, epochs: int = 200, lr: float = 1e-2, seed: int = 0,
                 input_scale: float = 255.0, position: bool = True, max_samples: int = 4000, device: str = "cpu",
                 threads: int | None = 1):
        self.hidden, self.layers, self.epochs, self.lr, self.seed = hidden, layers, epochs, lr, seed
        self.input_scale, self.position, self.device = input_scale, position, device
        self.max_samples = max_samples
        self.threads = threads
        self.net = None
        self.shape: tuple[int, int] | None = None
        self.reference: np.ndarray | None = None

    def _features(self, intensities, reference, rows, cols, shape) -> np.ndarray:
        n = len(rows)
        d = (intensities - reference).reshape(n, -1) / self.input_scale
        r = reference.reshape(n, -1) / self.input_scale
        parts = [d * 4.0, r]
        if self.position:
            parts.append(poly_terms(rows, cols, shape, 1)[:, 1:])
        return np.concatenate(parts, axis=1).astype(np.float32)

    def _draw(self, samples: Samples) -> np.ndarray:
        # Contact pixels carry the information; flat ones only pin the zero. Draw up to half
        # of the budget from each, the rest of the budget going to whichever has more.
        rng = np.random.default_rng(self.seed)
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

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        import torch

        train = self._draw(samples)
        x = self._features(samples.intensities, samples.reference, samples.rows, samples.cols, samples.shape)
        y = samples.normals[:, :2].astype(np.float32)
        x, y = x[train], y[train]
        self.shape = samples.shape
        if reference is not None:
            self.reference = np.asarray(reference, dtype=np.float32)
        with _deterministic(self.seed, self.threads):
            net = self._build(x.shape[1])
            xt = torch.from_numpy(x).to(self.device)
            yt = torch.from_numpy(y).to(self.device)
            opt = torch.optim.Adam(net.parameters(), lr=self.lr)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(self.epochs, 1))
            loss = torch.zeros(())
            for _ in range(self.epochs):
                opt.zero_grad()
                loss = torch.nn.functional.l1_loss(net(xt), yt)
                loss.backward()
                opt.step()
                sched.step()
        self.net = net.eval()
        rep = self._fit_report(samples)
        rep["final_l1_loss"] = float(loss.detach())
        return rep

    def _predict_features(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import torch

        with torch.no_grad(), _deterministic(self.seed, self.threads):
            out = self.net(torch.from_numpy(x).to(self.device)).cpu().numpy().astype(np.float64)
        r2 = np.sum(out ** 2, axis=1)
        # Outputs outside the unit disc have no normal: shrink them onto a 85-degree tilt.
        s = np.where(r2 > 0.996, np.sqrt(0.996 / np.maximum(r2, 1e-12)), 1.0)
        out = out * s[:, None]
        n = np.concatenate([out, np.sqrt(1.0 - np.sum(out ** 2, axis=1, keepdims=True))], axis=1)
        return n, np.isfinite(n).all(axis=1)

    def predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray]:
        return self._predict_features(self._features(samples.intensities, samples.reference, samples.rows,
                                                     samples.cols, samples.shape))

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
        n_img, p, h, w, c = images.shape
        rows, cols = (a.ravel() for a in np.mgrid[:h, :w])
        ref = self.reference.transpose(1, 2, 0, 3).reshape(h * w, p, c)
        grads, valid = [], []
        for img in images:
            obs = img.transpose(1, 2, 0, 3).reshape(h * w, p, c)
            n, ok = self._predict_features(self._features(obs, ref, rows, cols, (h, w)))
            gx, gy = normals_to_gradients(n)
            grads.append(np.stack([gx, gy], -1).reshape(h, w, 2))
            valid.append(ok.reshape(h, w))
        return np.stack(grads).astype(np.float32), np.stack(valid)

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {f"weights/{k.replace('.', '_')}": v.detach().cpu().numpy() for k, v in self.net.state_dict().items()}
        arrays["config"] = np.array([self.hidden, self.layers, int(self.position)], dtype=np.int64)
        if self.reference is not None:
            arrays["reference"] = self.reference
        return arrays
