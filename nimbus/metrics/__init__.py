"""Image-quality metrics shared by training and the benchmark: PSNR, SSIM (named protocols), LPIPS.

Modules:

* :mod:`nimbus.metrics.image`: the 8-bit round trip, PSNR and SSIM, validity masks; numpy
  (the benchmark, float64) or torch (training, on its device); the SSIM the training loss uses.
* :mod:`nimbus.metrics.lpips`: LPIPS v0.1 as a callable metric; its network
  (:mod:`~nimbus.metrics.lpips_network`), onnxruntime trunk (:mod:`~nimbus.metrics.lpips_onnx`)
  and weights, set up once with ``nimbus-bench setup-weights``
  (:mod:`~nimbus.metrics.lpips_weights`).

Examples
--------
>>> from nimbus.metrics import peak_signal_noise_ratio, structural_similarity
>>> peak_signal_noise_ratio(pred, gt)                       # doctest: +SKIP
>>> structural_similarity(pred, gt, protocol="skimage")    # doctest: +SKIP
"""

from nimbus.metrics.image import (MASK_PROTOCOL, PSNR_PROTOCOL, SSIM_PROTOCOLS, SSIMProtocol, get_ssim_protocol,
                                  mask_batch, masked_pair, mean_ssim, peak_signal_noise_ratio, quantize_8bit,
                                  ssim_map, structural_similarity)
from nimbus.metrics.lpips import LPIPS, LPIPS_BACKENDS, LPIPS_CPU_BACKEND
from nimbus.metrics.lpips_network import LPIPS_NETS, random_state_dict
from nimbus.metrics.lpips_weights import SETUP_COMMAND, WeightsMissing, setup_weights, weights_path

__all__ = [
    "LPIPS", "LPIPS_BACKENDS", "LPIPS_CPU_BACKEND", "LPIPS_NETS", "MASK_PROTOCOL", "PSNR_PROTOCOL", "SETUP_COMMAND",
    "SSIM_PROTOCOLS", "SSIMProtocol", "WeightsMissing", "get_ssim_protocol", "mask_batch", "masked_pair",
    "mean_ssim", "peak_signal_noise_ratio", "quantize_8bit", "random_state_dict", "setup_weights", "ssim_map",
    "structural_similarity", "weights_path",
]
