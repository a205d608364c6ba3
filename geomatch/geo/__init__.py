"""Geography: geodesy (WGS84, ECEF, local ENU frames), GPS fixes of images, and the similarity that
georeferences a model to them."""
