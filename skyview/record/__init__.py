"""Rerun recordings: a solve (`recording`) drawn through `draw`, the example cases (`cases`, `examples`),
sequences and tracking (`sequence`, `track`) and replay (`replay`)."""
