"""Reading a rerun recording back (the tests of icpflow.viz.recording and of the streaming CLI)."""

from collections import defaultdict

import numpy as np
from rerun.chunk import RrdReader


def read_recording(path) -> dict[str, dict[int, dict]]:
    """``{entity: {pair step: {component: numpy array}}}`` of an .rrd file, through rerun's RrdReader."""
    entities = defaultdict(dict)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if "pair" not in batch.schema.names:
            continue
        for row in range(batch.num_rows):
            step = batch.column("pair")[row].as_py()
            values = {}
            for name in batch.schema.names:
                if ":" in name:
                    value = batch.column(name)[row].as_py()
                    values[name.split(":", 1)[1]] = value if name.startswith("TextDocument") else np.asarray(value)
            entities[str(chunk.entity_path).lstrip("/")][step] = values
    return dict(entities)
