"""A small training helper: relMSE loss, Adam, fixed seed, and the mixing network's swap.

Enough to fit the tiny networks of :mod:`statmc.nn.nets` for a few dozen steps on the
toy renderer's exact truth (:mod:`statmc.toy`), on the CPU in seconds.  It is not a
training framework: no data loading, no checkpoints, no schedules.
"""

from __future__ import annotations

import inspect
import time

import torch

from statmc.errors import InputError, as_int, as_number

from .features import swap_mix_planes
from .ops import _readable, check_finite_tensor, check_like, check_tensor, torch_seed

__all__ = ["relmse_loss", "train", "random_swap", "swap_mix_loss", "RELMSE_EPS"]

#: ε of relMSE: 0.01 (Rousselle et al. 2011 §7), as in :func:`statmc.metrics.relmse`.
RELMSE_EPS = 0.01


def relmse_loss(x, ref, eps: float = RELMSE_EPS):
    """Relative MSE ``mean((x − r)² / (r² + ε))`` of tensors (differentiable).

    Parameters
    ----------
    x, ref : floating-point tensors of the same shape, dtype and device
        Not empty, finite.
    eps : float
        ε = 0.01 of §7 of Rousselle et al. 2011 (the value of :func:`statmc.metrics.relmse`,
        which this equals on the same numbers in any layout: the mean is over all entries).
        ``eps = 0`` needs a reference without zeros.

    Returns
    -------
    0-d tensor

    Raises
    ------
    InputError
        For anything else, and when the loss overflows the dtype (e.g. float16).

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
    if not x.is_floating_point():   # ints gave a silent result, bools a RuntimeError,
        raise InputError(f"`x` and `ref` must be floating-point tensors; got {x.dtype}.")  # complex a complex loss
    check_like("ref", ref, "x", x)
    if x.numel() == 0:              # the mean of nothing was a silent NaN
        raise InputError(f"`x` and `ref` must not be empty; got shape {tuple(x.shape)}.")
    check_finite_tensor("x", x)
    check_finite_tensor("ref", ref)
    eps = as_number("eps", eps, lo=0.0)
    if eps == 0.0 and _readable((ref == 0).any()):     # 0/0 was a silent NaN
        raise InputError(f"`eps` = 0 needs a reference without zeros; `ref` has "
                         f"{int((ref == 0).sum())}.  Use eps > 0 (default 0.01).")
    loss = torch.mean((x - ref) ** 2 / (ref * ref + eps))
    if _readable(torch.isfinite(loss)) is False:
        raise InputError(f"`x`: the loss overflowed {x.dtype} although `x` and `ref` are "
                         "finite; use float32 or float64, or rescale them.")
    return loss


def _check_loss(loss, step):
    """``InputError`` unless ``loss`` is a finite one-element tensor with a gradient."""
    if not isinstance(loss, torch.Tensor) or loss.numel() != 1:
        raise InputError(f"`loss_fn` must return a scalar tensor; got {loss!r} at step {step}.")
    if not loss.is_floating_point():     # complex: a RuntimeError deep in backward()
        raise InputError(f"`loss_fn` must return a real floating-point loss; got {loss.dtype} "
                         f"at step {step}.")
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
        With at least one trainable parameter.
    loss_fn : callable ``(model, step) -> 0-d tensor``
        Builds one step's loss, e.g. ``relmse_loss(net.denoise(features, image), truth)``
        on a fresh render per step; it must be computed from ``model``'s parameters.
    steps : int
        ``>= 0``.
    lr : float
        Adam's learning rate, ``> 0`` (default 3e-3: the rate that fitted the notebook's
        kernel network in a few dozen steps).
    seed : int
        In ``[0, 2**64 − 1]``.  Seeds torch's random state inside the run (restored
        afterwards), for any randomness in ``loss_fn`` or the model; the run is then
        reproducible.

    Returns
    -------
    dict
        ``losses`` (list of floats, one per step), and the run's configuration ``steps``,
        ``lr``, ``seed``, ``optimizer`` and ``seconds`` (wall clock).

    Raises
    ------
    InputError
        For bad arguments (a ``loss_fn`` that cannot be called as ``loss_fn(model, step)``
        among them); when ``loss_fn`` raises an ``InputError`` (re-raised naming
        ``loss_fn`` and the step); and when it returns something other than a real
        one-element tensor with a gradient, a NaN/Inf loss, or a loss from which no
        gradient reaches the model's parameters.  The run then stops before that step's
        optimiser update: the model keeps the weights of the last finite step.

    Notes
    -----
    The model is in training mode (``model.train()``) during the run and is left in
    evaluation mode (``model.eval()``), also when the run stops with an error.
    """
    if not isinstance(model, torch.nn.Module):
        raise InputError(f"`model` must be a torch.nn.Module; got {type(model).__name__}.")
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:    # none: torch's ValueError; all frozen: a misleading "no gradient"
        raise InputError(f"`model` must have trainable parameters (requires_grad=True); "
                         f"{type(model).__name__} has none.")
    _check_loss_fn(loss_fn)
    steps = as_int("steps", steps, lo=0)
    lr = as_number("lr", lr, lo=0.0, lo_open=True)
    top = min(float(torch.finfo(p.dtype).max) for p in params)
    if lr > top:      # a RuntimeError inside Adam's update
        raise InputError(f"`lr` must be at most {top:.3g}, the largest value of the model's "
                         f"parameter dtype; got {lr!r}.")
    seed = torch_seed("seed", seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    t0 = time.perf_counter()
    model.train()
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            for step in range(steps):
                try:
                    loss = loss_fn(model, step)
                except InputError as exc:   # e.g. relmse_loss passed as loss_fn itself
                    # same class (a FileFormatError stays one), the message naming loss_fn
                    raise type(exc)(f"`loss_fn` (called as loss_fn(model, step)) failed at "
                                    f"step {step}: {exc}") from exc
                _check_loss(loss, step)
                opt.zero_grad()
                loss.backward()
                if all(p.grad is None for p in params):     # Adam would skip them all
                    raise InputError(f"`loss_fn` returned a loss that does not depend on the "
                                     f"model's parameters (no gradient reached them at step "
                                     f"{step}): compute it from the `model` argument's output.")
                opt.step()
                losses.append(float(loss.detach()))
    finally:
        model.eval()
    return {"losses": losses, "steps": steps, "lr": lr, "seed": seed,
            "optimizer": "Adam", "seconds": time.perf_counter() - t0}


def _check_loss_fn(loss_fn):
    """``InputError`` unless ``loss_fn`` is callable with two positional arguments
    ``(model, step)`` (a one-argument function was a TypeError at step 0)."""
    if not callable(loss_fn):
        raise InputError(f"`loss_fn` must be callable as loss_fn(model, step); got {loss_fn!r}.")
    try:
        sig = inspect.signature(loss_fn)
    except (TypeError, ValueError):      # some builtins have none: left to the call
        return
    try:
        sig.bind(None, 0)
    except TypeError:
        raise InputError(f"`loss_fn` must be callable as loss_fn(model, step), with two "
                         f"positional arguments; got {getattr(loss_fn, '__name__', loss_fn)!r} "
                         f"with signature {sig}.") from None


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
    if not callable(loss):
        raise InputError(f"`loss` must be callable as loss(z, ref); got {loss!r}.")
    f, a, b, _ = random_swap(features, x, y, p=p, generator=generator)
    return loss(model.mix(f, a, b), ref)
