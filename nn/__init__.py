"""statmc.nn: small PyTorch networks whose outputs plug into statmc's kernels.

Installed as ``statmc.nn``; needs the optional ``torch`` extra (``pip install
'statmc[nn]'``, pinned to the CPU build ``torch==2.13.0``).  ``statmc`` never imports this
package (nor torch); this package imports ``statmc``.

* :mod:`statmc.nn.ops` — differentiable twins of the statmc kernels the networks feed:
  :func:`apply_kernels` (``statmc.analytic.apply_kernels``), :func:`combine` and
  :func:`combine_multi` (Back 2020 Eq. 8 and 14, ``statmc.combine``);
* :mod:`statmc.nn.features` — :func:`pixel_features`, the one input builder (from a
  :class:`statmc.PixelStats`);
* :mod:`statmc.nn.nets` — :class:`KernelNet`, :class:`CombinerNet`, :class:`MixNet`,
  :class:`SamplingNet`;
* :mod:`statmc.nn.train` — :func:`relmse_loss` and :func:`train` (Adam, fixed seed);
* :mod:`statmc.nn.layout` — conversions between statmc's channel-last arrays and NCHW
  tensors.

These networks are untrained plumbing, not a claim that learned beats classical: see
docs/nn.md.
"""

from .features import feature_channels, pixel_features
from .layout import (image_to_tensor, kernels_from_numpy, kernels_to_numpy, tensor_to_image,
                     weights_from_numpy, weights_to_numpy)
from .nets import CombinerNet, KernelNet, MixNet, SamplingNet
from .ops import ApplyKernels, Combine, CombineMulti, apply_kernels, combine, combine_multi
from .train import relmse_loss, train

__all__ = [
    "apply_kernels", "combine", "combine_multi", "ApplyKernels", "Combine", "CombineMulti",
    "pixel_features", "feature_channels",
    "KernelNet", "CombinerNet", "MixNet", "SamplingNet",
    "relmse_loss", "train",
    "image_to_tensor", "tensor_to_image", "kernels_from_numpy", "kernels_to_numpy",
    "weights_from_numpy", "weights_to_numpy",
]
