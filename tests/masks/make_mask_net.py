#!/usr/bin/env python3
"""Writes small ONNX networks for the mask-network tests (needs python3-onnx).

usage: make_mask_net.py OUT_DIR

  texture.onnx       a fixed-weight saliency net for the sim rig: the rock is
                     textured, the table and the disc are smooth. Input
                     1x3xHxW normalised with mean 0.5, std 0.25 per channel
                     (the first convolution undoes that); a Laplacian of the
                     grey level, squared, box-averaged: output 1x1xHxW logits
                     k * (local energy - t).
  texture_prob.onnx  the same with a Sigmoid at the end (a probability).
  three_maps.onnx    a 1x3xHxW output: not a mask network (wrong output shape).

Every graph is built with onnx.helper from fixed weights; nothing is trained.
"""
import os
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

MEAN, STD = 0.5, 0.25
OPSET = 11


def conv(name, x, y, w, b, pad):
    inits = [numpy_helper.from_array(w.astype(np.float32), name + "_w"),
             numpy_helper.from_array(b.astype(np.float32), name + "_b")]
    node = helper.make_node("Conv", [x, name + "_w", name + "_b"], [y], pads=[pad] * 4,
                            kernel_shape=list(w.shape[2:]))
    return node, inits


def save(path, nodes, inits, out_channels):
    graph = helper.make_graph(
        nodes, "mask_test_net",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("saliency", TensorProto.FLOAT, [1, out_channels, "H", "W"])],
        inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="aggscan tests")
    model.ir_version = 7
    onnx.checker.check_model(model)
    onnx.save(model, path)


def texture_net(sigmoid):
    # Conv 3x3: Laplacian of the grey level v = mean over channels of
    # STD * x + MEAN (the mean cancels: a Laplacian's weights sum to 0).
    lap = np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], dtype=np.float64)
    w1 = np.stack([lap * STD / 3.0] * 3)[None]
    n1, i1 = conv("lap", "image", "hp", w1, np.zeros(1), 1)
    sq = helper.make_node("Mul", ["hp", "hp"], ["energy"])
    # Conv box blur with scale and threshold: logit = k * (local energy - t).
    # t: the granite-like sim rock at 640 x 480 lies well above it, the smooth
    # table and disc well below; the disc rim's edges reach it only in a thin
    # ring, which the refinement drops (it keeps the largest region).
    r, t = 7, 0.01
    k = 4.0 / t
    w2 = np.full((1, 1, 2 * r + 1, 2 * r + 1), k / (2 * r + 1) ** 2)
    n2, i2 = conv("blur", "energy", "logit" if sigmoid else "saliency", w2, np.array([-k * t]), r)
    nodes, inits = [n1, sq, n2], i1 + i2
    if sigmoid:
        nodes.append(helper.make_node("Sigmoid", ["logit"], ["saliency"]))
    return nodes, inits


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    save(os.path.join(out, "texture.onnx"), *texture_net(False), 1)
    save(os.path.join(out, "texture_prob.onnx"), *texture_net(True), 1)
    n, i = conv("rgb", "image", "saliency", np.eye(3).reshape(3, 3, 1, 1), np.zeros(3), 0)
    save(os.path.join(out, "three_maps.onnx"), [n], i, 3)


if __name__ == "__main__":
    main()
