"""The lander's dimensions (body frame: origin on the flattened ground at the lander centre).

:mod:`sim.world.terrain` builds the lander from them; the scenario schema checks robot
starts, waypoints and the lander's place against them (without importing the terrain
module, which imports the schema).
"""

LANDER_DECK_HALF = (0.8, 0.8, 0.3)  # deck box half extents
LANDER_DECK_Z = 1.0  # deck centre height
LANDER_FOOT_XY = 1.1  # footpad centres at (+-1.1, +-1.1): 2.5 m wide with the pads
LANDER_FOOT_RADIUS = 0.15
LANDER_LEG_RADIUS = 0.05
LANDER_RADIUS = 1.8  # footprint circle, pads included
LANDER_PAD_RADIUS = 2.2  # terrain is flat under the lander out to here ...
LANDER_PAD_BLEND_M = 1.5  # ... and blends back to the natural terrain over this width
