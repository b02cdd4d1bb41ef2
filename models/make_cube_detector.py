"""Build ``models/cube_detector.onnx``: a detector of the SO-101 scene's magenta cube with the RT-DETR signature.

No public package ships an RT-DETR model, so this one is made from ordinary ONNX operators: a
colour threshold (red and blue both well above green: the cube, not the yellow arm nor the blue
floor), the mask's extents as a box, its pixel count as the score. The signature is RT-DETR's:
input ``images`` ``(1, 3, 320, 320)`` RGB in ``[0, 1]``; outputs ``logits`` ``(1, 1, 1)`` (one
query, one class, before the sigmoid) and ``boxes`` ``(1, 1, 4)`` (normalised centre x, centre y,
width, height). Any RT-DETR export plugs into the same detector.

Run:  uv run python models/make_cube_detector.py [--out models/cube_detector.onnx]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

SIZE = 320
MARGIN = 0.12
"""How far red and blue must each exceed green (in [0, 1]) for a pixel to be the cube's."""
MIN_PIXELS = 6.0
"""Pixels of cube colour below which the score stays low."""


def _const(name: str, value: np.ndarray) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value, dtype=np.float32), name)


def build() -> onnx.ModelProto:
    ramp = (np.arange(SIZE, dtype=np.float32) + 0.0) / SIZE
    initializers = [
        _const("margin", np.array(MARGIN)),
        _const("x_start", ramp.reshape(1, 1, 1, SIZE)),
        _const("x_end", (ramp + 1.0 / SIZE).reshape(1, 1, 1, SIZE)),
        _const("y_start", ramp.reshape(1, 1, SIZE, 1)),
        _const("y_end", (ramp + 1.0 / SIZE).reshape(1, 1, SIZE, 1)),
        _const("one", np.array(1.0)),
        _const("two", np.array(2.0)),
        _const("cap", np.array(MIN_PIXELS + 10.0)),
        _const("offset", np.array(MIN_PIXELS)),
        numpy_helper.from_array(np.array([1, 1, 1], dtype=np.int64), "logits_shape"),
        numpy_helper.from_array(np.array([1, 1, 4], dtype=np.int64), "boxes_shape"),
        numpy_helper.from_array(np.array([2], dtype=np.int64), "axis_h"),
        numpy_helper.from_array(np.array([3], dtype=np.int64), "axis_w"),
    ]
    nodes = [
        helper.make_node("Split", ["images"], ["r", "g", "b"], axis=1, num_outputs=3),
        helper.make_node("Sub", ["r", "g"], ["r_g"]),
        helper.make_node("Sub", ["b", "g"], ["b_g"]),
        helper.make_node("Greater", ["r_g", "margin"], ["red_enough"]),
        helper.make_node("Greater", ["b_g", "margin"], ["blue_enough"]),
        helper.make_node("And", ["red_enough", "blue_enough"], ["is_cube"]),
        helper.make_node("Cast", ["is_cube"], ["mask"], to=TensorProto.FLOAT),
        # Occupied columns and rows.
        helper.make_node("ReduceMax", ["mask", "axis_h"], ["columns"], keepdims=1),
        helper.make_node("ReduceMax", ["mask", "axis_w"], ["rows"], keepdims=1),
        # x1 = max over occupied columns of their right edge; x0 = 1 - max(columns * (1 - left edge)).
        helper.make_node("Mul", ["columns", "x_end"], ["col_end"]),
        helper.make_node("ReduceMax", ["col_end"], ["x1"], keepdims=0),
        helper.make_node("Sub", ["one", "x_start"], ["x_from_right"]),
        helper.make_node("Mul", ["columns", "x_from_right"], ["col_start"]),
        helper.make_node("ReduceMax", ["col_start"], ["x0_flipped"], keepdims=0),
        helper.make_node("Sub", ["one", "x0_flipped"], ["x0"]),
        helper.make_node("Mul", ["rows", "y_end"], ["row_end"]),
        helper.make_node("ReduceMax", ["row_end"], ["y1"], keepdims=0),
        helper.make_node("Sub", ["one", "y_start"], ["y_from_bottom"]),
        helper.make_node("Mul", ["rows", "y_from_bottom"], ["row_start"]),
        helper.make_node("ReduceMax", ["row_start"], ["y0_flipped"], keepdims=0),
        helper.make_node("Sub", ["one", "y0_flipped"], ["y0"]),
        # cx, cy, w, h.
        helper.make_node("Add", ["x0", "x1"], ["x_sum"]),
        helper.make_node("Div", ["x_sum", "two"], ["cx"]),
        helper.make_node("Add", ["y0", "y1"], ["y_sum"]),
        helper.make_node("Div", ["y_sum", "two"], ["cy"]),
        helper.make_node("Sub", ["x1", "x0"], ["w"]),
        helper.make_node("Sub", ["y1", "y0"], ["h"]),
        helper.make_node("Unsqueeze", ["cx", "zero_axis"], ["cx1"]),
        helper.make_node("Unsqueeze", ["cy", "zero_axis"], ["cy1"]),
        helper.make_node("Unsqueeze", ["w", "zero_axis"], ["w1"]),
        helper.make_node("Unsqueeze", ["h", "zero_axis"], ["h1"]),
        helper.make_node("Concat", ["cx1", "cy1", "w1", "h1"], ["box"], axis=0),
        helper.make_node("Reshape", ["box", "boxes_shape"], ["boxes"]),
        # Score: the pixel count, capped, minus the minimum (a logit: sigmoid(count - 6)).
        helper.make_node("ReduceSum", ["mask"], ["count"], keepdims=0),
        helper.make_node("Min", ["count", "cap"], ["capped"]),
        helper.make_node("Sub", ["capped", "offset"], ["score"]),
        helper.make_node("Reshape", ["score", "logits_shape"], ["logits"]),
    ]
    initializers.append(numpy_helper.from_array(np.array([0], dtype=np.int64), "zero_axis"))
    graph = helper.make_graph(
        nodes,
        "cube_detector",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, SIZE, SIZE])],
        [
            helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, 1, 1]),
            helper.make_tensor_value_info("boxes", TensorProto.FLOAT, [1, 1, 4]),
        ],
        initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], producer_name="openral")
    model.ir_version = 9
    helper.set_model_props(
        model,
        {
            "labels": '["cube"]',
            "description": "colour-threshold detector of the SO-101 scene's cube (RT-DETR signature)",
        },
    )
    onnx.checker.check_model(model, full_check=True)
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("cube_detector.onnx"))
    args = parser.parse_args()
    onnx.save(build(), args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
