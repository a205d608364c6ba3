"""The pair list of the small synthetic scene (seed 1, 2 aerial + 4 ground) that the gRPC
end-to-end test and the export tests map: one list, so both keep mapping the same model.

Every ground pair, both aerial images, and for each aerial image its two best ground partners
(measured) rather than all eight aerial x ground pairs: those are tiled (several matchings each),
and half of them connect the model as well as all of them."""

from __future__ import annotations

GROUND = [f"ground_0{i}.png" for i in range(4)]
PAIRS = [(a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :]] + [
    ("aerial_00.png", "aerial_01.png"),
    ("aerial_00.png", "ground_00.png"),
    ("aerial_00.png", "ground_01.png"),
    ("aerial_01.png", "ground_02.png"),
    ("aerial_01.png", "ground_03.png"),
]
