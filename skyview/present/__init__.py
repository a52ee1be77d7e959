"""Steps and results as drawables, for every sink alike: one palette, one stretch, one label layout
(`drawables`, `image`, `text`). Imports no sink."""
