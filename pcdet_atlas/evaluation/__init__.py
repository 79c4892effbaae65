"""Evaluation: exact 3D IoU, the Waymo L1/L2 AP/APH metric, attack success rate and analyses."""
