"""The authors' released MMM checkpoints: key maps (keys.py) and the importer (importer.py)."""
