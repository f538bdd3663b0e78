"""ROS bags in and out: ``import_bag`` (ROS 1, ROS 2 sqlite3, MCAP) and ``export_bag`` (MCAP).

Needs the ``bag`` extra (``pip install sonarset[bag]``: rosbags).
"""

from sonarset.ingest.bag.export import export_bag
from sonarset.ingest.bag.importer import import_bag, load_bag

__all__ = ["export_bag", "import_bag", "load_bag"]
