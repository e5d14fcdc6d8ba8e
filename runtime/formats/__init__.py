"""The file formats of models_spec/, one module a page: dataset, rig, natural labels, and
atomic writes for all of them."""
