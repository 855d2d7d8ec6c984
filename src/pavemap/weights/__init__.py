"""Weight files: the shipped detector (``pavemap-yolov5n-rdd2022.pt``, package data beside this module, its
MODEL_CARD.md with it) and :mod:`pavemap.weights.registry`, the one home of the files pavemap knows and
their expected sha256."""
