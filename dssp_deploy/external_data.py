"""The files an ONNX graph pulls in: the ``location`` of every tensor stored as external data.

An ONNX file may keep tensors in other files (``*.onnx.data``), named by a ``location`` relative to the
graph file. ONNX Runtime, given a graph's bytes, reads them relative to the *current directory*, and no
manifest hash covers them. The runtime therefore lists them first (:func:`external_locations`, reading the
protobuf wire format directly: no ``onnx`` package on the robot), checks each one as a file of the model
directory with its own size and sha256 (``dssp_deploy.manifest.read_graph_files``) and hands ONNX Runtime
those checked bytes (``dssp_deploy.sessions.open_session``): every byte a session loads is inside the
model directory and hashed.

Walked: the model's graph and functions (and training graphs), every graph's initializers, sparse
initializers and nodes, every node attribute's tensors and subgraphs (If/Loop/Scan bodies, at any depth).
"""

from __future__ import annotations

from collections.abc import Iterator

# Field numbers of onnx.proto (onnx/onnx.proto3): (message, field) → the message that field holds.
MODEL, GRAPH, NODE, ATTRIBUTE, TENSOR, SPARSE, FUNCTION, TRAINING, ENTRY = range(9)
CHILDREN = {
    MODEL: {7: GRAPH, 20: TRAINING, 25: FUNCTION},
    TRAINING: {1: GRAPH, 2: GRAPH},
    FUNCTION: {7: NODE, 11: ATTRIBUTE},
    GRAPH: {1: NODE, 5: TENSOR, 15: SPARSE},
    NODE: {5: ATTRIBUTE},
    ATTRIBUTE: {5: TENSOR, 6: GRAPH, 10: TENSOR, 11: GRAPH, 22: SPARSE, 23: SPARSE},
    SPARSE: {1: TENSOR, 2: TENSOR},
}
TENSOR_EXTERNAL_DATA, TENSOR_DATA_LOCATION, EXTERNAL = 13, 14, 1  # TensorProto.external_data, .data_location, EXTERNAL
ENTRY_KEY, ENTRY_VALUE = 1, 2  # StringStringEntryProto
MAX_DEPTH = 64  # nested graphs; a deeper one is not an exported graph


class MalformedGraph(ValueError):
    """The bytes are not a well-formed ONNX protobuf."""


def _varint(data: bytes, at: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if at >= len(data) or shift > 63:
            raise MalformedGraph(f"a varint runs past byte {at}")
        byte = data[at]
        value |= (byte & 0x7F) << shift
        at, shift = at + 1, shift + 7
        if not byte & 0x80:
            return value, at


def _fields(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int | tuple[int, int]]]:
    """(field number, wire type, value) of one message: an int for varints, (start, end) for length-delimited."""
    at = start
    while at < end:
        key, at = _varint(data, at)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, at = _varint(data, at)
            yield number, wire, value
        elif wire == 2:
            length, at = _varint(data, at)
            if at + length > end:
                raise MalformedGraph(f"field {number} runs past its message (byte {at + length} > {end})")
            yield number, wire, (at, at + length)
            at += length
        elif wire in (1, 5):
            at += 8 if wire == 1 else 4
        else:
            raise MalformedGraph(f"wire type {wire} of field {number} at byte {at}")
    if at != end:
        raise MalformedGraph(f"a field runs past its message end {end}")


def _tensor_location(data: bytes, start: int, end: int) -> tuple[bool, str | None]:
    """(stored as external data?, its location) of one TensorProto."""
    external, location = False, None
    for number, wire, value in _fields(data, start, end):
        if number == TENSOR_DATA_LOCATION and wire == 0:
            external = external or value == EXTERNAL
        elif number == TENSOR_EXTERNAL_DATA and wire == 2:
            external = True
            key = text = None
            for n, w, v in _fields(data, *value):
                if w == 2 and n in (ENTRY_KEY, ENTRY_VALUE):
                    s = data[v[0] : v[1]].decode("utf-8", errors="replace")
                    key, text = (s, text) if n == ENTRY_KEY else (key, s)
            if key == "location":
                location = text
    return external, location


def external_locations(data: bytes) -> list[str | None]:
    """The ``location`` of every tensor of the ONNX model ``data`` stored as external data, in file order,
    each once (None for an external tensor without a location). Raises :class:`MalformedGraph`.

    Bytes without the key ``location`` name no file (ONNX Runtime refuses an external tensor without one)
    and are not walked: exported graphs keep their weights inside, so loading them costs one search."""
    if b"location" not in data:
        return []
    found: dict[str | None, None] = {}
    stack = [(MODEL, 0, len(data), 0)]
    while stack:
        kind, start, end, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise MalformedGraph(f"graphs nested deeper than {MAX_DEPTH}")
        if kind == TENSOR:
            external, location = _tensor_location(data, start, end)
            if external:
                found.setdefault(location)
            continue
        children = CHILDREN[kind]
        inner = [(children[n], *v, depth + 1) for n, w, v in _fields(data, start, end) if w == 2 and n in children]
        stack.extend(reversed(inner))
    return list(found)
