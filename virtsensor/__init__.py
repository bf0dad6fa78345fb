"""virtsensor: a real-time virtual sensor of the front tyres' self-aligning torque.

Estimates the front-left and front-right SAT from 12 signals a car already
carries on its CAN bus (El Mrhasli, Monsuez, Mouton, VEHICULAR 2023).
Importing the package is cheap: heavy modules load on first use.
"""

__version__ = "0.1.0"
