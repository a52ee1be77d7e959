"""Known truth: the sensor image renderer (`render`), the papers' scenarios (`scenarios`), the truth of a rendered
frame (`truth`) and the scoring of an identification against it (`scoring`).

Nothing below it (core, io, detect, identify) imports it: truth never enters an identifier."""
