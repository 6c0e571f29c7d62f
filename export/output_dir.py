"""Write a model directory all at once or not at all (the rules of :mod:`dssp_core.output_guard`).

Files are written into a temporary sibling directory (``.NAME.partial-XXXX`` next to MODEL_DIR) and the
whole directory is renamed into place at the end; on any failure (an error, a failed parity check,
Ctrl-C) the temporary directory — and any parent directories this export created — are removed.

What may already be at MODEL_DIR:
- nothing, or an empty directory: it is (re)placed;
- a previous export (a ``dssp_model.json`` manifest, and no files but those it lists): refused unless
  ``force``; with ``force`` the new directory is swapped in, then the old one deleted;
- anything else (a file, a directory with other content): always refused — export never deletes what it
  did not write.
"""

from __future__ import annotations

import json
from pathlib import Path

from dssp_core.errors import ExportError
from dssp_core.files import read_regular_text
from dssp_core.output_guard import OutputDir, OutputKind
from dssp_deploy.manifest import MANIFEST_NAME, is_model_dir


def _is_own_model_dir(path: Path) -> bool:
    """A previous export: its manifest, and only the files the manifest lists (ONNX external data too)."""
    if not is_model_dir(path):
        return False
    files = json.loads(read_regular_text(path / MANIFEST_NAME) or "{}").get("files")
    if not isinstance(files, dict):
        return all(p.suffix in (".onnx", ".pt", ".json", ".data") for p in path.iterdir())
    listed = set(files) | {MANIFEST_NAME}
    return all(p.name in listed or any(p.name.startswith(f"{name}.") for name in files) for p in path.iterdir())


MODEL_DIR = OutputKind("a DSSP model directory", "python -m export.to_onnx", signature=_is_own_model_dir, marker=False)
"""``python -m export.to_onnx -o``: recognised by its manifest; no marker file is added to a model directory."""


class StagedDirectory(OutputDir):
    """A temporary sibling of ``out`` that becomes ``out`` on :meth:`commit`, and vanishes otherwise.

    with StagedDirectory(out, force) as stage:
        write files into stage.path
        stage.commit()
    """

    def __init__(self, out: Path, force: bool = False):
        super().__init__(out, MODEL_DIR, force=force, flag="-o", staged=True, error=ExportError)
