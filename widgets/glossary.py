"""What each of the console's terms means, said once: the tooltips of the words and figures that carry them
(issue 50: S_z, F_ts, ε and RMSE were on the screen with nothing to explain them)."""

GLOSSARY = {
    "S_z": "The paper's switch for the z axis: POSITION (S_z = 1), the operator moves the TSI; FORCE (S_z = 0), "
           "the robot presses the tissue through the force ramp (Fig. 4)",
    "F_d": "F_d, the desired force: the level of the ramp the robot is pressing to now",
    "F_ts": "F_ts, the measured force: the tactile array's pressures summed over its face (the TSI's reading)",
    "epsilon": "ε, the settling threshold: a level is recorded once the force's RMSE about F_d stays below it",
    "rmse": "RMSE, the root-mean-square error of the measured force about F_d over the settle window: how "
            "steady the press is",
    "ladder": "The ramp's force levels, F_min to F_max: a level turns green once it is recorded",
    "indentation": "How deep the TSI face has pressed into the tissue since it first touched, in mm (the depth "
                   "the paper's rule reads a tumour's depth from)",
    "contact_area": "The area of the elements that touch the tissue now (each element is 2 x 2 mm)",
    "peak_pressure": "The highest pressure any element reads now; the ramp stops short of the element ceiling",
    "centre_of_pressure": "Where on the face the load is centred, from the TSI's centre: x along the 4-element "
                          "axis, y along the 15-element one",
    "region_done": "The paper's region-done flag: every level of this area is recorded and the probe lifts; "
                   "move to the next area",
    "phase": "Where the palpation is in the paper's flowchart (Fig. 4): approach, seeking contact, settling "
             "at a level, recording, retract, done",
}
