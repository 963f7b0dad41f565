"""Elman-network surrogate (000 Sec. 4.1): parameters -> model outputs (e.g. the first four frequencies).

Network: ``torch.nn.RNN`` (tanh) is exactly the Elman network (hidden layer + context layer holding
the previous hidden output, W_ih x + W_hh h_prev + b). A static input vector is presented for
``n_steps`` time steps (context starting at zero) and the last hidden state is mapped to the outputs by
a linear layer, so the context feedback acts as a learned refinement of the hidden features.
Inputs are standardised log-parameters and outputs standardised (optionally log-) responses, which
makes the map smooth (frequency ~ sqrt(E/rho) is linear in logs).

Training (a choice; 000 trained the weights with PSO): Adam followed by full-batch L-BFGS on the mean
squared error, which reaches far lower error than PSO for a few hundred weights; a held-out split
(000: 3:1) gives R^2, MAPE and RMSE per output (000 Eqs. 35-37). torch is imported lazily.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maglev_ros.errors import UserError


@dataclass(frozen=True)
class SurrogateScore:
    r2: tuple[float, ...]
    mape_percent: tuple[float, ...]
    rmse: tuple[float, ...]
    n_test: int

    def to_dict(self) -> dict:
        return {"r2": list(self.r2), "mape_percent": list(self.mape_percent), "rmse": list(self.rmse),
                "n_test": self.n_test}


def score(y_true: np.ndarray, y_pred: np.ndarray) -> SurrogateScore:
    yt, yp = np.atleast_2d(y_true), np.atleast_2d(y_pred)
    ss_res = np.sum((yt - yp) ** 2, axis=0)
    ss_tot = np.sum((yt - yt.mean(axis=0)) ** 2, axis=0)
    r2 = 1 - ss_res / np.where(ss_tot > 0, ss_tot, np.finfo(float).tiny)
    with np.errstate(divide="ignore", invalid="ignore"):
        mape = 100 * np.mean(np.abs((yp - yt) / yt), axis=0)
    rmse = np.sqrt(np.mean((yt - yp) ** 2, axis=0))
    return SurrogateScore(tuple(map(float, r2)), tuple(map(float, mape)), tuple(map(float, rmse)), yt.shape[0])


class ElmanSurrogate:
    """fit(X (n, d) positive parameters or any reals, Y (n, k)) -> self; predict(X) -> (n, k)."""

    def __init__(self, hidden: int = 24, n_steps: int = 3, log_inputs: bool = True, log_outputs: bool = True,
                 adam_epochs: int = 600, lbfgs_iter: int = 300, lr: float = 0.01, seed: int = 0,
                 threads: int | None = 1):
        self.hidden, self.n_steps = int(hidden), int(n_steps)
        self.log_inputs, self.log_outputs = bool(log_inputs), bool(log_outputs)
        self.adam_epochs, self.lbfgs_iter, self.lr, self.seed = int(adam_epochs), int(lbfgs_iter), float(lr), seed
        self.threads = threads
        self._net = None

    # transforms ------------------------------------------------------------------------------
    def _tx(self, X):
        X = np.atleast_2d(np.asarray(X, dtype=float))
        return (np.log(X) if self.log_inputs else X)

    def _ty(self, Y):
        Y = np.atleast_2d(np.asarray(Y, dtype=float))
        return (np.log(Y) if self.log_outputs else Y)

    def fit(self, X, Y) -> "ElmanSurrogate":
        import torch
        if self.threads:
            torch.set_num_threads(int(self.threads))
        tx, ty = self._tx(X), self._ty(Y)
        if tx.shape[0] != ty.shape[0] or tx.shape[0] < 4 or not (np.all(np.isfinite(tx)) and np.all(np.isfinite(ty))):
            raise UserError("surrogate: expected >= 4 finite samples with matching rows (positive values for log transforms)")
        self._xm, self._xs = tx.mean(0), np.where(tx.std(0) > 0, tx.std(0), 1.0)
        self._ym, self._ys = ty.mean(0), np.where(ty.std(0) > 0, ty.std(0), 1.0)
        torch.manual_seed(self.seed if self.seed is not None else 0)
        xt = torch.tensor((tx - self._xm) / self._xs, dtype=torch.float64)
        yt = torch.tensor((ty - self._ym) / self._ys, dtype=torch.float64)
        rnn = torch.nn.RNN(tx.shape[1], self.hidden, batch_first=True, nonlinearity="tanh").double()
        head = torch.nn.Linear(self.hidden, ty.shape[1]).double()
        params = list(rnn.parameters()) + list(head.parameters())

        def forward(x):
            seq = x[:, None, :].expand(-1, self.n_steps, -1)
            out, _ = rnn(seq)
            return head(out[:, -1, :])

        opt = torch.optim.Adam(params, lr=self.lr)
        for _ in range(self.adam_epochs):
            opt.zero_grad()
            loss = torch.mean((forward(xt) - yt) ** 2)
            loss.backward()
            opt.step()
        if self.lbfgs_iter > 0:
            lb = torch.optim.LBFGS(params, lr=1.0, max_iter=self.lbfgs_iter, tolerance_grad=1e-12,
                                   tolerance_change=1e-14, history_size=50, line_search_fn="strong_wolfe")

            def closure():
                lb.zero_grad()
                l = torch.mean((forward(xt) - yt) ** 2)
                l.backward()
                return l
            lb.step(closure)
        self._forward = forward
        self._net = (rnn, head)
        with torch.no_grad():
            self.train_mse_ = float(torch.mean((forward(xt) - yt) ** 2))
        return self

    def predict(self, X) -> np.ndarray:
        if self._net is None:
            raise UserError("surrogate: call fit() before predict()")
        import torch
        tx = (self._tx(X) - self._xm) / self._xs
        with torch.no_grad():
            z = self._forward(torch.tensor(tx, dtype=torch.float64)).numpy()
        y = z * self._ys + self._ym
        return np.exp(y) if self.log_outputs else y


def train_and_score(X, Y, test_fraction: float = 0.25, seed: int = 0, **kw) -> tuple[ElmanSurrogate, SurrogateScore]:
    """Random train/test split (000: 3:1), fit on train, score on the held-out part; the returned
    surrogate is then refitted on all samples."""
    X, Y = np.atleast_2d(X), np.atleast_2d(Y)
    rng = np.random.default_rng(seed)
    idx = rng.permutation(X.shape[0])
    n_test = max(1, int(round(test_fraction * X.shape[0])))
    te, tr = idx[:n_test], idx[n_test:]
    s = ElmanSurrogate(seed=seed, **kw).fit(X[tr], Y[tr])
    sc = score(Y[te], s.predict(X[te]))
    return ElmanSurrogate(seed=seed, **kw).fit(X, Y), sc
