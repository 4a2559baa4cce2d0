"""The LPIPS trunks run by onnxruntime: the same convolutions, in less CPU time than torch's.

The trunks dominate the cost of scoring (VGG16 on 320 x 240 is ~47 GFLOP per image).
onnxruntime's CPU convolutions (blocked NCHWc kernels) run the VGG trunk at ~0.25 CPU
seconds per 320 x 240 image here, about the core's float32 FMA peak, ~1.2x less CPU time
than torch's oneDNN path (``tools/speed/metrics.py``; AlexNet: about equal).  The
ONNX graph is written here directly from :data:`nimbus.metrics.lpips_network.TRUNKS` and the
weights, as ONNX protobuf bytes: a chain of ``MaxPool`` / ``Conv`` / ``Relu`` whose
tapped ``Relu`` outputs are the graph's outputs.  Building it takes a fraction of a
second, so nothing is cached on disk and no exporter (``torch.onnx``, the ``onnx``
package) is needed; the tests check the graph with ``onnx.checker`` where ``onnx`` is
installed.

Only the trunk runs here.  The input normalisation, the per-pixel unit normalisation of
the tapped features and the distance stay in :class:`nimbus.metrics.lpips_network.LPIPSNetwork`, so
both back ends share them; LPIPS values agree with the torch path to ~1e-7.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch

from nimbus.metrics.lpips_network import TRUNKS

#: ONNX opset and IR version of the written graph (Conv, Relu, MaxPool: unchanged since opset 12).
OPSET = 17
IR_VERSION = 8
INPUT = "x"
_FLOAT = 1  # TensorProto.FLOAT
_ATTR_INTS = 7  # AttributeProto.INTS


# --- protobuf wire format (only what an ONNX graph of this shape needs) ------------------------
def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _int(field: int, value: int) -> bytes:
    return _varint(field << 3) + _varint(value)


def _bytes(field: int, value: bytes | str) -> bytes:
    if isinstance(value, str):
        value = value.encode()
    return _varint((field << 3) | 2) + _varint(len(value)) + value


def _ints_attr(name: str, values) -> bytes:
    # AttributeProto: name 1, ints 8 (repeated int64), type 20.
    return _bytes(1, name) + b"".join(_int(8, int(v)) for v in values) + _int(20, _ATTR_INTS)


def _node(op: str, inputs, outputs, name: str, attrs: bytes = b"") -> bytes:
    # NodeProto: input 1, output 2, name 3, op_type 4, attribute 5 (each attribute its own field).
    return (b"".join(_bytes(1, i) for i in inputs) + b"".join(_bytes(2, o) for o in outputs)
            + _bytes(3, name) + _bytes(4, op) + attrs)


def _tensor(name: str, array: np.ndarray) -> bytes:
    # TensorProto: dims 1, data_type 2, name 8, raw_data 9 (little-endian).
    a = np.ascontiguousarray(array, dtype="<f4")
    return b"".join(_int(1, d) for d in a.shape) + _int(2, _FLOAT) + _bytes(8, name) + _bytes(9, a.tobytes())


def _value_info(name: str, dims) -> bytes:
    # ValueInfoProto{name 1, type 2: TypeProto{tensor_type 1: {elem_type 1, shape 2: {dim 1: {value 1 | param 2}}}}}
    shape = b"".join(_bytes(1, _int(1, d) if isinstance(d, int) else _bytes(2, d)) for d in dims)
    return _bytes(1, name) + _bytes(2, _bytes(1, _int(1, _FLOAT) + _bytes(2, shape)))


def trunk_model_bytes(net: str, state_dict: Mapping[str, torch.Tensor]) -> bytes:
    """ONNX model (serialised ModelProto) of the trunk of ``net`` with the weights of ``state_dict``.

    Parameters
    ----------
    net : {"alex", "vgg"}
    state_dict : mapping
        :class:`nimbus.metrics.lpips_network.LPIPSNetwork` layout (``convs.{i}.weight/bias``; heads ignored).

    Returns
    -------
    bytes
        A graph with input ``x``: (B, 3, H, W) float32, already ImageNet-normalised as in
        :meth:`nimbus.metrics.lpips_network.LPIPSNetwork.features`, and one output ``tap{k}`` per tapped
        layer: the raw (not unit-normalised) ReLU output (B, C_k, H_k, W_k).
    """
    nodes, inits, outputs = [], [], []
    x = INPUT
    for i, s in enumerate(TRUNKS[net]):
        if s.pool_before is not None:
            k, st = s.pool_before
            attrs = _bytes(5, _ints_attr("kernel_shape", (k, k))) + _bytes(5, _ints_attr("strides", (st, st)))
            nodes.append(_node("MaxPool", [x], [f"pool{i}"], f"pool{i}", attrs))
            x = f"pool{i}"
        w, b = f"convs.{i}.weight", f"convs.{i}.bias"
        inits += [_tensor(w, state_dict[w].detach().cpu().numpy()), _tensor(b, state_dict[b].detach().cpu().numpy())]
        attrs = (_bytes(5, _ints_attr("kernel_shape", (s.kernel, s.kernel)))
                 + _bytes(5, _ints_attr("strides", (s.stride, s.stride)))
                 + _bytes(5, _ints_attr("pads", (s.padding,) * 4)))
        nodes.append(_node("Conv", [x, w, b], [f"conv{i}"], f"conv{i}", attrs))
        out = f"tap{len(outputs)}" if s.tap else f"relu{i}"
        nodes.append(_node("Relu", [f"conv{i}"], [out], f"relu{i}"))
        if s.tap:
            outputs.append((out, s.out_ch))
        x = out
    graph = (b"".join(_bytes(1, n) for n in nodes) + _bytes(2, f"lpips-{net}-trunk")
             + b"".join(_bytes(5, t) for t in inits)
             + _bytes(11, _value_info(INPUT, ("batch", 3, "height", "width")))
             + b"".join(_bytes(12, _value_info(name, ("batch", c, f"{name}_h", f"{name}_w"))) for name, c in outputs))
    opset = _bytes(1, "") + _int(2, OPSET)  # OperatorSetIdProto: domain 1 (default), version 2
    # ModelProto: ir_version 1, producer_name 2, graph 7, opset_import 8.
    return _int(1, IR_VERSION) + _bytes(2, "nimbus-bench") + _bytes(7, graph) + _bytes(8, opset)


class OnnxTrunk:
    """The trunk of ``net`` as an onnxruntime CPU session; called on normalised (B, 3, H, W) arrays.

    Parameters
    ----------
    net : {"alex", "vgg"}
    state_dict : mapping
        Weights (see :func:`trunk_model_bytes`).
    threads : int, optional
        Intra-op threads (default: ``torch.get_num_threads()``, so both back ends use the same).
    """

    def __init__(self, net: str, state_dict: Mapping[str, torch.Tensor], threads: int | None = None) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        opts.intra_op_num_threads = int(threads or torch.get_num_threads())
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(trunk_model_bytes(net, state_dict), opts,
                                            providers=["CPUExecutionProvider"])
        self.outputs = [o.name for o in self.session.get_outputs()]

    def __call__(self, x: np.ndarray) -> list[np.ndarray]:
        """Raw tapped ReLU outputs, one (B, C_k, H_k, W_k) float32 array per tap."""
        return self.session.run(self.outputs, {INPUT: np.ascontiguousarray(x, dtype=np.float32)})

