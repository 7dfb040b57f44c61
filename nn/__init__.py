"""statmc.nn: small PyTorch networks whose outputs plug into statmc's kernels.

Installed as ``statmc.nn``; needs the optional ``torch`` extra (``pip install
'statmc[nn]'``, pinned to the CPU build ``torch==2.13.0``).  ``statmc`` never imports this
package (nor torch); this package imports ``statmc``.

* :mod:`statmc.nn.ops` — differentiable twins of the statmc kernels the networks feed:
  :func:`apply_kernels` (``statmc.analytic.apply_kernels``), :func:`combine` and
  :func:`combine_multi` (Back 2020 Eq. 8 and 14, ``statmc.combine``);
* :mod:`statmc.nn.features` — :func:`pixel_features`, the input builder (from a
  :class:`statmc.PixelStats`), and :func:`mix_features` (with :func:`mix_inputs` and
  :func:`swap_mix_planes`), the swappable inputs of the mixing network of Firmino 2022 §4.3;
* :mod:`statmc.nn.nets` — :class:`KernelNet`, :class:`CombinerNet`, :class:`MixNet`,
  :class:`SamplingNet`;
* :mod:`statmc.nn.train` — :func:`relmse_loss`, :func:`train` (Adam, fixed seed), and
  :func:`random_swap` / :func:`swap_mix_loss` (the random swapping of Firmino 2022 §4.3);
* :mod:`statmc.nn.layout` — conversions between statmc's channel-last arrays and NCHW
  tensors.

These networks are untrained plumbing, not a claim that learned beats classical: see
docs/nn.md.
"""

from .features import (MIX_PLANES, MIX_SWAP, feature_channels, mix_feature_channels, mix_features,
                       mix_features_of, mix_inputs, pixel_features, swap_mix_planes)
from .layout import (image_to_tensor, kernels_from_numpy, kernels_to_numpy, tensor_to_image,
                     weights_from_numpy, weights_to_numpy)
from .nets import CombinerNet, KernelNet, MixNet, SamplingNet
from .ops import ApplyKernels, Combine, CombineMulti, apply_kernels, combine, combine_multi
from .train import random_swap, relmse_loss, swap_mix_loss, train

__all__ = [
    "apply_kernels", "combine", "combine_multi", "ApplyKernels", "Combine", "CombineMulti",
    "pixel_features", "feature_channels", "mix_features", "mix_features_of", "mix_inputs",
    "mix_feature_channels", "swap_mix_planes", "MIX_PLANES", "MIX_SWAP",
    "KernelNet", "CombinerNet", "MixNet", "SamplingNet",
    "relmse_loss", "train", "random_swap", "swap_mix_loss",
    "image_to_tensor", "tensor_to_image", "kernels_from_numpy", "kernels_to_numpy",
    "weights_from_numpy", "weights_to_numpy",
]
