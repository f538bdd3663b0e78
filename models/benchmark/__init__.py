"""The open benchmark (``sonarset benchmark``): protocol v1, frozen in code, run into one results
file that names its protocol version, so that results from other machines compare.

- ``protocol``: what v1 (and the quick subset's v1-quick) simulates, draws and scores;
- ``stores``: the protocol's stores, simulated on first use into a cache and reused;
- ``run``: every model against flow and the ceilings on every dataset, into results.json / .md;
- ``tables``: the Markdown of one results file, and of several side by side.
"""

from sonarset.models.benchmark.protocol import PROTOCOL_V1, PROTOCOL_V1_QUICK, Dataset, Protocol, StoreRecipe
from sonarset.models.benchmark.run import run_benchmark
from sonarset.models.benchmark.stores import cache_dir
from sonarset.models.benchmark.tables import compare_results, load_results, results_markdown

__all__ = ["PROTOCOL_V1", "PROTOCOL_V1_QUICK", "Dataset", "Protocol", "StoreRecipe", "cache_dir", "compare_results",
           "load_results", "results_markdown", "run_benchmark"]
