"""The work cell every layer shares: the world frame and the table (lowest layer, data only).

World frame: z up, floor at z = 0, table top at z = :data:`TABLE_TOP_Z`; +x from the robot
base into the workspace, +y to the robot's left. Arms bolt to the table top.
"""

#: Height of the table top (m); arm bases stand on it.
TABLE_TOP_Z = 0.75
#: Table top extent in the world frame: x from TABLE_X[0] to TABLE_X[1], y within
#: +-TABLE_HALF_Y (m).
TABLE_X = (-0.25, 0.85)
TABLE_HALF_Y = 0.75
TABLE_THICKNESS = 0.04

#: The volume over the table, up to 1.2 m above it (the xArm7's links reach ~0.65 m up):
#: (lower corner, upper corner) in the world frame. The twin's guard keeps robot links inside
#: it unless the embodiment names its own box; the operator's IK keeps them off its back face.
TABLE_WORKSPACE_BOX = (
    (TABLE_X[0], -TABLE_HALF_Y, TABLE_TOP_Z),
    (TABLE_X[1], TABLE_HALF_Y, TABLE_TOP_Z + 1.2),
)
