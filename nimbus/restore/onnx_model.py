"""A user-supplied image-to-image restorer in ONNX, run with onnxruntime on the CPU (``restorer=onnx:PATH``).

The model's contract
--------------------
Input: one tensor, float32 NCHW ``(1, 3, H, W)``, RGB in [0, 1] (no normalisation).
Output: its first output, float32 ``(1, 3, H, W)``, RGB in [0, 1] (values outside are clipped).
A model with dynamic spatial axes runs at the image's size; one with a fixed size gets the
image resized to it (bicubic) and its output resized back (bilinear).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.onnx_session import open_image_model

_FIX = "give restorer=onnx:PATH/TO/MODEL.onnx (float32 NCHW RGB in [0, 1] in and out)"


class OnnxRestorer:
    """An ONNX image-to-image model (module docstring); raises NimbusError when it cannot be used."""

    def __init__(self, path: str | Path) -> None:
        model = open_image_model(path, "restorer model", _FIX, _FIX)
        self.session, self.input_name, self.fixed_size, self.path = (model.session, model.input_name,
                                                                     model.fixed_size, model.path)
        self.sha256 = hashlib.sha256(self.path.read_bytes()).hexdigest()

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The restored ``image`` (H, W, 3) float32 in [0, 1]."""
        h, w = image.shape[:2]
        x = np.asarray(image, np.float32)
        if self.fixed_size is not None and self.fixed_size != (w, h):
            x = cv2.resize(x, self.fixed_size, interpolation=cv2.INTER_CUBIC)
        try:
            out = self.session.run(None, {self.input_name: np.ascontiguousarray(x.transpose(2, 0, 1)[None])})[0]
        except Exception as e:  # a graph that does not fit the input fails only when run
            raise NimbusError(f"restorer model {self.path} failed on a {w} x {h} image ({e}); {_FIX}") from None
        out = np.asarray(out, np.float32)
        if out.ndim != 4 or out.shape[:2] != (1, 3):
            raise NimbusError(f"restorer model {self.path} returned shape {out.shape}; expected (1, 3, H, W)")
        out = out[0].transpose(1, 2, 0)
        if out.shape[:2] != (h, w):
            out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
        return np.clip(np.nan_to_num(out, nan=0.0), 0.0, 1.0).astype(np.float32)
