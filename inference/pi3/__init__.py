"""Clean-room π³ and π³X (github yyfz/Pi3): networks, strict checkpoint loading, the
conversion of their outputs to :class:`swiftjax.prediction.ChunkPrediction`, the official
resize rule, the golden self-check and ONNX export.

Modules: ``config`` (sizes, presets), ``model`` (π³ and the shared trunk), ``pi3x`` (π³X),
``conditioning`` (π³X's intrinsics / depth / pose conditions), ``heads``, ``decoders``,
``checkpoint``, ``convert``, ``preprocess``, ``golden``, ``onnx``.
"""
