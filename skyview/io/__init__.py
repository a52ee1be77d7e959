"""Files in and out: FITS images, the FITS WCS a solution is written as, atomic writes.

Imports only `skyview.core`."""
