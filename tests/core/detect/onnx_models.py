"""ONNX models for the detector tests: real graphs re-sized to another input, and tiny synthetic
graphs with a family's output layout.

``resized`` makes, from a shipped fixed-size export, the same network at another square input size:
the weights are untouched; only the shapes that the exporter froze change. Convolutions, pooling
and scale-based resizes do not depend on the input size; the exporters froze it in the input, the
outputs' anchor counts and the channel-shuffle ``Reshape`` targets of the ShuffleNet/ESNet backbones
(``[1, 2, C, H, W]`` and ``[1, C', H, W]``). Those spatial entries are rescaled, stride by stride.
This is not the official export at that size (those are trained at it), but it is the same
computation a size-agnostic export runs, which is what the detector's sizing must follow.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

STRIDES = (2, 4, 8, 16, 32, 64, 128)


def _grid(size: int, stride: int) -> int:
    return math.ceil(size / stride)


def resized(src: Path, dst: Path, size: int) -> Path:
    """Write ``src`` (a square 1x3xSxS export) re-sized to ``size`` x ``size`` as ``dst``."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(src))
    g = model.graph
    inp = g.input[0]
    old = inp.type.tensor_type.shape.dim[2].dim_value
    assert old and inp.type.tensor_type.shape.dim[3].dim_value == old, "a square fixed-size input"
    new_of = {_grid(old, s): _grid(size, s) for s in STRIDES}
    for d in (2, 3):
        inp.type.tensor_type.shape.dim[d].dim_value = size

    def fix(shape: np.ndarray) -> np.ndarray | None:
        """The reshape target with its spatial (last two) entries rescaled, or None if unchanged."""
        if shape.ndim != 1 or len(shape) not in (4, 5) or shape[0] != 1:
            return None
        out = shape.copy()
        for i in (-2, -1):
            if int(out[i]) in new_of:
                out[i] = new_of[int(out[i])]
        return None if np.array_equal(out, shape) else out

    reshape_shapes = {n.input[1] for n in g.node if n.op_type == "Reshape"}
    for init in g.initializer:
        if init.name in reshape_shapes:
            arr = fix(numpy_helper.to_array(init))
            if arr is not None:
                init.CopyFrom(numpy_helper.from_array(arr.astype(np.int64), init.name))
    for node in g.node:
        if node.op_type == "Constant" and node.output[0] in reshape_shapes:
            arr = fix(numpy_helper.to_array(node.attribute[0].t))
            if arr is not None:
                node.attribute[0].t.CopyFrom(numpy_helper.from_array(arr.astype(np.int64)))
    # Output anchor counts: per stride (GFL heads) or summed over 8/16/32 (YOLOX)
    by_count = {_grid(old, s) ** 2: s for s in STRIDES}
    yolox_rows = sum(_grid(old, s) ** 2 for s in (8, 16, 32))
    for out in g.output:
        dim = out.type.tensor_type.shape.dim[1]
        n = dim.dim_value
        if n == yolox_rows:
            dim.dim_value = sum((size // s) ** 2 for s in (8, 16, 32))
        elif n in by_count:
            dim.dim_value = _grid(size, by_count[n]) ** 2
    del g.value_info[:]  # intermediate shapes of the old size: let the runtime infer them anew
    onnx.save(model, str(dst))
    return dst


def synthetic(dst: Path, input_shape: list[int | str], outputs: dict[str, np.ndarray],
              elem_type: int | None = None) -> Path:
    """A graph whose outputs are the given constants whatever its input (of ``input_shape``): a
    family's output layout with chosen values, for the decoder's sizing without a trained net."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes, outs = [], []
    for name, value in outputs.items():
        nodes.append(helper.make_node("Constant", [], [name],
                                      value=numpy_helper.from_array(value.astype(np.float32))))
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(value.shape)))
    inp = helper.make_tensor_value_info("images", elem_type or TensorProto.FLOAT, input_shape)
    graph = helper.make_graph(nodes, "synthetic", [inp], outs)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(dst))
    return dst
