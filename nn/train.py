"""A small training helper: relMSE loss, Adam, fixed seed, and the mixing network's swap.

Enough to fit the tiny networks of :mod:`statmc.nn.nets` for a few dozen steps on the
toy renderer's exact truth (:mod:`statmc.toy`), on the CPU in seconds.  It is not a
training framework: no data loading, no checkpoints, no schedules.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from statmc.errors import InputError, as_number

from .features import swap_mix_planes
from .ops import check_finite_tensor, check_like, check_tensor

__all__ = ["relmse_loss", "train", "random_swap", "swap_mix_loss", "RELMSE_EPS"]

#: ε of relMSE: 0.01 (Rousselle et al. 2011 §7), as in :func:`statmc.metrics.relmse`.
RELMSE_EPS = 0.01


def relmse_loss(x, ref, eps: float = RELMSE_EPS):
    """Relative MSE ``mean((x − r)² / (r² + ε))`` of tensors (differentiable).

    Parameters
    ----------
    x, ref : tensors of the same shape
    eps : float
        ε = 0.01 of §7 of Rousselle et al. 2011 (the value of :func:`statmc.metrics.relmse`,
        which this equals on the same numbers in any layout: the mean is over all entries).

    Returns
    -------
    0-d tensor

    References
    ----------
    F. Rousselle, C. Knaus, M. Zwicker. "Adaptive Sampling and Reconstruction using Greedy
    Error Minimization". ACM Trans. Graph. 30(6), 159, 2011.
    https://doi.org/10.1145/2070781.2024193
    """
    if not isinstance(x, torch.Tensor) or not isinstance(ref, torch.Tensor):
        raise InputError(f"`x` and `ref` must be torch tensors; got {type(x).__name__} and "
                         f"{type(ref).__name__}.")
    if x.shape != ref.shape:
        raise InputError(f"`ref` must have the shape of `x` {tuple(x.shape)}; got {tuple(ref.shape)}.")
    check_like("ref", ref, "x", x)
    check_finite_tensor("x", x)
    check_finite_tensor("ref", ref)
    eps = as_number("eps", eps, lo=0.0)
    return torch.mean((x - ref) ** 2 / (ref * ref + eps))


def _check_loss(loss, step):
    """``InputError`` unless ``loss`` is a finite one-element tensor with a gradient."""
    if not isinstance(loss, torch.Tensor) or loss.numel() != 1:
        raise InputError(f"`loss_fn` must return a scalar tensor; got {loss!r} at step {step}.")
    if not loss.requires_grad:
        raise InputError(f"`loss_fn` returned a loss without a gradient at step {step} "
                         "(requires_grad is False): it must be computed from the "
                         "model's output, outside torch.no_grad().")
    if not bool(torch.isfinite(loss.detach()).all()):
        raise InputError(f"`loss_fn` returned a non-finite loss ({float(loss.detach())}) "
                         f"at step {step}; stopped before the optimiser step, so the "
                         f"model keeps the weights it had after {step} steps.")


def train(model, loss_fn, steps: int, *, lr: float = 3e-3, seed: int = 0) -> dict:
    """Fit ``model`` with Adam: ``steps`` times ``loss = loss_fn(model, step)``, backward, step.

    Parameters
    ----------
    model : torch.nn.Module
    loss_fn : callable ``(model, step) -> 0-d tensor``
        Builds one step's loss, e.g. ``relmse_loss(net.denoise(features, image), truth)``
        on a fresh render per step.
    steps : int
    lr : float
        Adam's learning rate (default 3e-3: the rate that fitted the notebook's kernel
        network in a few dozen steps).
    seed : int
        Seeds torch's random state inside the run (restored afterwards), for any
        randomness in ``loss_fn`` or the model; the run is then reproducible.

    Returns
    -------
    dict
        ``losses`` (list of floats, one per step), and the run's configuration ``steps``,
        ``lr``, ``seed``, ``optimizer`` and ``seconds`` (wall clock).

    Raises
    ------
    InputError
        For bad arguments, and when ``loss_fn`` returns something other than a one-element
        tensor with a gradient, or a NaN/Inf loss.  The run then stops before that step's
        optimiser update: the model keeps the weights of the last finite step.

    Notes
    -----
    The model is in training mode (``model.train()``) during the run and is left in
    evaluation mode (``model.eval()``), also when the run stops with an error.
    """
    if not isinstance(model, torch.nn.Module):
        raise InputError(f"`model` must be a torch.nn.Module; got {type(model).__name__}.")
    if not callable(loss_fn):
        raise InputError(f"`loss_fn` must be callable as loss_fn(model, step); got {loss_fn!r}.")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise InputError(f"`steps` must be an int >= 0; got {steps!r}.")
    lr = as_number("lr", lr, lo=0.0, lo_open=True)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise InputError(f"`seed` must be an int; got {seed!r}.")
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    t0 = time.perf_counter()
    model.train()
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            for step in range(int(steps)):
                loss = loss_fn(model, step)
                _check_loss(loss, step)
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(float(loss.detach()))
    finally:
        model.eval()
    return {"losses": losses, "steps": int(steps), "lr": lr, "seed": int(seed),
            "optimizer": "Adam", "seconds": time.perf_counter() - t0}


def random_swap(features, x, y, *, p: float = 0.5, generator=None):
    """The random swapping of Firmino 2022 §4.3 on a batch, per sample with probability ``p``.

    A swapped sample exchanges the render and the denoised image *with their error
    estimates*: its :func:`~statmc.nn.mix_features` planes go through
    :func:`~statmc.nn.swap_mix_planes` ((HDR, VAR) ↔ (DEN, SURE); ``σ² f'(x)`` and
    ``‖y − x‖²`` stay), and ``(x, y)`` becomes ``(y, x)``.  ``MixNet.mix`` of the result is
    then ``y + β (x − y)`` on swapped samples: the network predicts β = 1 − α of Eq. 10
    there, and Eq. 9's α elsewhere, for the same target ``z``.

    Parameters
    ----------
    features : (N, 6C, H, W) tensor
        :func:`~statmc.nn.mix_features` planes (batched with ``torch.cat``).
    x, y : (N, C, H, W) tensors
        Renders and their denoised images.
    p : float
        Probability of a swap, in [0, 1] (the paper: "randomly", 1/2 here by default).
    generator : torch.Generator, optional
        Source of the draws; default torch's global generator, which :func:`train` seeds.

    Returns
    -------
    features, x, y : tensors
        The batch with the swapped samples swapped (new tensors; the inputs are untouched).
    swapped : (N,) bool tensor

    Raises
    ------
    InputError
        For tensors of the wrong shape, dtype or device, NaN or Inf in ``features``, ``x``
        or ``y`` (as the ops of :mod:`statmc.nn.ops`), or ``p`` outside [0, 1].
    """
    check_tensor("features", features, 4, "(N, 6C, H, W)")
    check_tensor("x", x, 4, "(N, C, H, W)")
    check_tensor("y", y, 4, "(N, C, H, W)")
    if y.shape != x.shape:
        raise InputError(f"`y` must have the shape of `x` {tuple(x.shape)}; got {tuple(y.shape)}.")
    N, C, H, W = x.shape
    if features.shape != (N, 6 * C, H, W):
        raise InputError(f"`features` must be (N, 6C, H, W) = {(N, 6 * C, H, W)} for images "
                         f"{tuple(x.shape)} (mix_features planes); got {tuple(features.shape)}.")
    check_like("y", y, "x", x)
    check_like("features", features, "x", x)
    # the outputs hold exactly the inputs' values, so a NaN/Inf would pass through silently
    for name, t in (("features", features), ("x", x), ("y", y)):
        check_finite_tensor(name, t)
    p = as_number("p", p, lo=0.0)
    if p > 1.0:
        raise InputError(f"`p` must be a probability in [0, 1]; got {p!r}.")
    if generator is not None and not isinstance(generator, torch.Generator):
        raise InputError(f"`generator` must be a torch.Generator or None; got {generator!r}.")
    swapped = torch.rand(N, generator=generator) < p
    m = swapped.to(x.device).view(N, 1, 1, 1)
    return (torch.where(m, swap_mix_planes(features), features), torch.where(m, y, x),
            torch.where(m, x, y), swapped)


def swap_mix_loss(model, features, x, y, ref, *, p: float = 0.5, loss=relmse_loss,
                  generator=None):
    """The mixing network's training loss with the random swapping of Firmino 2022 §4.3.

    ``loss(model.mix(f', x', y'), ref)`` with ``(f', x', y')`` from :func:`random_swap`:
    on a swapped sample the network sees (DEN, SURE) in the render's slot and (HDR, VAR)
    in the denoised one, and the loss is that of ``y + β (x − y)``, β its output.  Without
    the swap (``p=0``) this is the plain loss of ``x + α (y − x)``, whose minimum in
    practice is α = 1 when the denoised image is usually better (docs/nn.md, §4.3).

    Parameters
    ----------
    model : MixNet
        With ``inputs="mix"``.
    features : (N, 6C, H, W) tensor
        :func:`~statmc.nn.mix_features` planes.
    x, y, ref : (N, C, H, W) tensors
        Renders, denoised images, and the reference (truth).
    p, generator
        Of :func:`random_swap`.
    loss : callable ``(z, ref) -> 0-d tensor``
        Default :func:`relmse_loss` (the paper trains with SMAPE, §5.3).

    Returns
    -------
    0-d tensor
    """
    if getattr(model, "inputs", None) != "mix":
        raise InputError("`model` must be a MixNet(inputs='mix'): the swap permutes "
                         "mix_features planes.")
    f, a, b, _ = random_swap(features, x, y, p=p, generator=generator)
    return loss(model.mix(f, a, b), ref)
