"""The exported network's pillar sums as ONNX Runtime runs them quickest on one thread: ``ScatterND(reduction="add")``.

The export writes each pillar sum (``fastflow3d.network.scatter.scatter_sum``) as ``ScatterElements(reduction="add",
axis=1)`` on the transposed rows: correct on any number of threads, but ONNX Runtime adds its elements one by one
(2.2-5.6 ms per 60k points x 33 channels). ``ScatterND(reduction="add")`` adds whole rows, 12x quicker, but ONNX Runtime
splits its updates over its intra-op threads without atomics, so two threads adding into one pillar race (sums off by
up to 1.0 with 2 threads: onnxruntime's GitHub issue 18048). On one thread it adds in the same order as
ScatterElements: the same sums bit for bit.

:func:`sequential_scatter_sums` rewrites an exported graph for a session of ONE intra-op thread (what
``fastflow3d.artifact.engines`` opens for ``threads=1``, the network of an overlapped stream on 2 cores,
``fastflow3d.inference.stream.overlap_threads``): each such ScatterElements becomes

    Transpose(ScatterND(Transpose(data), Unsqueeze(ids, 1), rows, reduction="add"))

where ``rows`` (P, C) is what the export transposed into the updates, then drops the nodes whose outputs nothing reads
any more (ONNX Runtime would still run the unused index Expand and row Transpose, 5 ms a KITTI pair) and the constants
only they read. On one thread the int8 network then takes about 0.7x the exported graph's time on a synthetic or a
KITTI pair (BENCHMARKS.md, "Student latency and the stream"). Only the export's own pattern is rewritten: ``ids``
a 1-D tensor unsqueezed on axis 0 and expanded over the channels (or not expanded, for constant data of one row: the
counts, as ONNX Runtime's optimiser leaves them); anything else is left as it is.
"""

from __future__ import annotations

import numpy as np


def sequential_scatter_sums(model) -> int:
    """Rewrite the ``onnx.ModelProto`` ``model`` in place for a one-thread session (module docstring); returns how many
    scatters were rewritten (0: the model is unchanged)."""
    from onnx import helper, numpy_helper

    graph = model.graph
    producer = {name: node for node in graph.node for name in node.output}
    constants = {tensor.name: numpy_helper.to_array(tensor) for tensor in graph.initializer}
    nodes, rewritten = [], 0
    for node in graph.node:
        ids = _pillar_ids(node, producer, constants, helper)
        if ids is None:
            nodes.append(node)
            continue
        data, _, updates = node.input
        prefix = f"{node.name or node.output[0]}_sequential"
        rows = _transposed_input(producer.get(updates), helper)
        if rows is None:
            rows = f"{prefix}_rows"
            nodes.append(helper.make_node("Transpose", [updates], [rows], perm=[1, 0]))
        axis = f"{prefix}_axis"
        graph.initializer.append(numpy_helper.from_array(np.array([1], np.int64), axis))
        nodes += [
            helper.make_node("Cast", [ids], [f"{prefix}_ids"], to=7),  # ScatterND takes int64 indices
            helper.make_node("Unsqueeze", [f"{prefix}_ids", axis], [f"{prefix}_index"]),
            helper.make_node("Transpose", [data], [f"{prefix}_data"], perm=[1, 0]),
            helper.make_node(
                "ScatterND", [f"{prefix}_data", f"{prefix}_index", rows], [f"{prefix}_sums"], reduction="add"
            ),
            helper.make_node("Transpose", [f"{prefix}_sums"], [node.output[0]], perm=[1, 0]),
        ]
        rewritten += 1
    if rewritten:
        outputs = {output.name for output in graph.output}
        del graph.node[:]
        graph.node.extend(_used(nodes, outputs))
        read = outputs | {name for node in graph.node for name in node.input}
        kept = [tensor for tensor in graph.initializer if tensor.name in read]
        del graph.initializer[:]
        graph.initializer.extend(kept)  # ONNX Runtime warns about each initializer no node reads
    return rewritten


def _pillar_ids(node, producer, constants, helper) -> str | None:
    """The 1-D ids tensor of an export's pillar sum (module docstring), or None when ``node`` is not one."""
    if node.op_type != "ScatterElements" or node.domain not in ("", "ai.onnx") or len(node.input) != 3:
        return None
    attributes = {attribute.name: helper.get_attribute_value(attribute) for attribute in node.attribute}
    if attributes.get("axis") != 1 or attributes.get("reduction") not in (b"add", "add"):
        return None
    unsqueeze = producer.get(node.input[1])
    if unsqueeze is not None and unsqueeze.op_type == "Expand":
        unsqueeze = producer.get(unsqueeze.input[0])
    else:  # no expansion (an optimiser drops it for one channel): only where the data has that one row
        data = constants.get(node.input[0])
        if data is None or data.ndim != 2 or data.shape[0] != 1:
            return None
    if unsqueeze is None or unsqueeze.op_type != "Unsqueeze" or len(unsqueeze.input) != 2:
        return None
    axes = constants.get(unsqueeze.input[1])
    if axes is None or axes.reshape(-1).tolist() != [0]:
        return None
    return unsqueeze.input[0]


def _transposed_input(node, helper) -> str | None:
    """The input of ``node`` when it is a 2-D transpose (perm [1, 0]), else None."""
    if node is None or node.op_type != "Transpose":
        return None
    perm = [helper.get_attribute_value(attribute) for attribute in node.attribute if attribute.name == "perm"]
    return node.input[0] if perm and list(perm[0]) == [1, 0] else None


def _used(nodes: list, outputs: set) -> list:
    """``nodes`` without those whose outputs neither a graph output nor a kept node reads (repeated to a fixpoint);
    all of them where a node holds a subgraph (it may read any outer name)."""
    if any(attribute.g.node or attribute.graphs for node in nodes for attribute in node.attribute):
        return nodes
    while True:
        read = set(outputs) | {name for node in nodes for name in node.input}
        kept = [node for node in nodes if any(name in read for name in node.output)]
        if len(kept) == len(nodes):
            return kept
        nodes = kept
