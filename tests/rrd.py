"""Reading a saved Rerun recording back with Rerun's own loader (``rerun.chunk.RrdReader``)."""

from collections import defaultdict


def read_rrd(path):
    """({entity path: sorted tick values it was logged on}, {static entity paths}, {entity: [component names]})."""
    from rerun.chunk import RrdReader

    ticks, static, components = defaultdict(list), set(), defaultdict(set)
    for chunk in RrdReader(str(path)).store().stream():
        batch, entity = chunk.to_record_batch(), chunk.entity_path.lstrip("/")
        components[entity].update(n for n in batch.schema.names if ":" in n)
        if chunk.is_static:
            static.add(entity)
        elif "tick" in batch.schema.names:
            ticks[entity].extend(batch.column("tick").to_pylist())
    return {k: sorted(v) for k, v in ticks.items()}, static, components


def text_rows(path, entity):
    """The texts logged at ``entity``, in tick order."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(str(path)).store().stream():
        if chunk.entity_path.lstrip("/") == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            rows += zip(batch.column("tick").to_pylist(), [t[0] for t in batch.column("TextLog:text").to_pylist()])
    return [text for _, text in sorted(rows)]
