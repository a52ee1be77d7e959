"""Image to attitude: the pipeline (`pipeline`), its result (`result`), the typed API (`api`: `skyview.solve`,
`Solver`, `Solution`), sequences of frames (`sequence`) and tracking (`track`; a tracked frame's
identification is `skyview.identify.tracking`).

What the CLI, the viewer and the recorder call."""
