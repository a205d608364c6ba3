"""Structure-from-Motion around COLMAP: pair planning (and retrieval), the COLMAP database and its
tracks, the view-graph check, mapping, and COLMAP's log and database copies."""
