"""Studies: the experiments behind every reported figure, each a small config run by one stage runner.

The top layer: it drives the other packages (collect, train, export, evaluate) through their Python entry
points and nothing imports it. A study's record (JSON, committed) holds every figure; its report is rebuilt
from the record alone (``python -m studies.report``).
"""
