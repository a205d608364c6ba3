"""The map of a survey: a surface model (DSM) and an orthophoto from a georeferenced sparse model.

What a drone team looks at first, made the way OpenDroneMap's ``--fast-orthophoto`` makes it:
from the sparse points and the cameras, without a dense reconstruction. One module per step:

- ``survey.py``: the model read for mapping (cameras, poses, points) in the model's projected
  CRS (``export.georef.ModelFrame``: UTM of the site for GPS, the GCP file's frame for GCPs);
  a model that is not georeferenced is refused, never mapped in a guessed CRS;
- ``grid.py``: a north-up raster grid in that CRS and sampling on it;
- ``dsm.py``: the surface model (robust per cell, outliers out, holes filled);
- ``photos.py``: the photos at working size through a cache bounded in bytes, and their
  projections;
- ``gains.py``: exposure balanced between photos from what overlapping photos see;
- ``mosaic.py``: one tile of the orthophoto (the photo that sees each place best, visibility
  on the DSM, feathered seams);
- ``cog.py``: Cloud-Optimized GeoTIFFs (rasterio + rio-cogeo);
- ``overlay.py``: the cameras and GCPs placed on the map's preview (the console's map);
- ``accuracy.py``: an orthophoto's position error against a reference (tests, bench/ortho.py);
- ``make.py``: the whole map of a run folder, tile by tile (``make_map``; ``map_step`` as a
  stage of a run or a reconstruct job).
"""

from __future__ import annotations

from .make import DSM_PATH, ORTHO_PATH, MapOptions, MapResult, make_map, map_step
from .survey import OrthoError

__all__ = ["DSM_PATH", "ORTHO_PATH", "MapOptions", "MapResult", "OrthoError", "make_map", "map_step"]
