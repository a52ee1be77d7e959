"""Stars in an image: background, segmentation and centroids (`centroids`), the centroider at the scale of
a photograph's stars (`stars`), broken trails taken out (`trails`), and the prediction windows of tracking
(`windows`).

Imports `skyview.core` and `skyview.io`."""
