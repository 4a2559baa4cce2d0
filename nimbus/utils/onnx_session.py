"""Opening a user's ONNX image model with onnxruntime (CPU), with one clear error for a file that will not do."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nimbus.errors import NimbusError


@dataclass(frozen=True)
class ImageModelSession:
    """An onnxruntime session of a model with one NCHW image input.

    Attributes
    ----------
    session : onnxruntime.InferenceSession
    input_name : str
    fixed_size : (width, height) or None
        The input's spatial size when the model fixes it; None for dynamic axes.
    path : Path
    """

    session: Any
    input_name: str
    fixed_size: tuple[int, int] | None
    path: Path


def open_image_model(path: str | Path, what: str, missing_fix: str, load_fix: str) -> ImageModelSession:
    """The session of the ONNX model at ``path``; ``what`` names it in messages (``"depth model"``).

    Raises
    ------
    NimbusError
        The file does not exist (the message ends with ``missing_fix``), onnxruntime cannot load it
        (``load_fix``), or it does not take exactly one 4-D (NCHW) input.
    """
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"{what} {path} does not exist; {missing_fix}")
    try:
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for bad files
        raise NimbusError(f"{what} {path} could not be loaded by onnxruntime ({e}); {load_fix}") from None
    inputs = session.get_inputs()
    if len(inputs) != 1 or len(inputs[0].shape) != 4:
        raise NimbusError(f"{what} {path} must take one NCHW image input, has {[(i.name, i.shape) for i in inputs]}")
    shape = inputs[0].shape
    fixed = (shape[3], shape[2]) if all(isinstance(s, int) and s > 0 for s in shape[2:]) else None
    return ImageModelSession(session, inputs[0].name, fixed, path)
