"""Photos to a dataset: photo reading, board detection, board identity, the pipeline and its benchmark."""
