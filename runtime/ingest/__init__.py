"""Photos to a dataset: photo reading, board detection, board identity and the pipeline."""
