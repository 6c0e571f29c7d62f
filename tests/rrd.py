"""Reading a saved Rerun recording back with Rerun's own loader (``rerun.chunk.RrdReader``)."""

import warnings
from collections import defaultdict


def _chunks(path):
    """Every chunk of the recording; a file streamed without its footer (a live stream saved by a server, a run that
    crashed) is read whole, without the footer's index (Rerun warns about that: expected here)."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="RRD file has no footer")
        reader = RrdReader(str(path))
    return reader.stream()


def read_rrd(path):
    """({entity path: sorted tick values it was logged on}, {static entity paths}, {entity: [component names]})."""
    ticks, static, components = defaultdict(list), set(), defaultdict(set)
    for chunk in _chunks(path):
        batch, entity = chunk.to_record_batch(), chunk.entity_path.lstrip("/")
        components[entity].update(n for n in batch.schema.names if ":" in n)
        if chunk.is_static:
            static.add(entity)
        elif "tick" in batch.schema.names:
            ticks[entity].extend(batch.column("tick").to_pylist())
    return {k: sorted(v) for k, v in ticks.items()}, static, components


def text_rows(path, entity):
    """The texts logged at ``entity``, in tick order."""
    rows = []
    for chunk in _chunks(path):
        if chunk.entity_path.lstrip("/") == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            rows += zip(batch.column("tick").to_pylist(), [t[0] for t in batch.column("TextLog:text").to_pylist()])
    return [text for _, text in sorted(rows)]
