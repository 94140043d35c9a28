"""Where the pose iterations start (no torch: the command-line parsers read it).

* ``"coarse"``: the box pose, then the coarse network;
* ``"templates"``: the detection mask matched against silhouette templates;
* ``"appearance"``: the same templates ranked by appearance as well (the image inside the mask
  against textured renderings, :mod:`cosy_lite.nets.appearance_templates`): a box and its flipped
  twin have one silhouette but not one print.

Both template starts need detection masks and no coarse network.
"""

STARTS = ("coarse", "templates", "appearance")
TEMPLATE_STARTS = ("templates", "appearance")
