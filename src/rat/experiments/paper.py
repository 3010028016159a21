"""The paper's own numbers, for reports that put ours beside them."""

from __future__ import annotations

#: The paper's table 1 (mean, std over seeds, %), keyed by (scenario, row task). Rows of the
#: manipulation scenario are the victim's task; rows of the opposite scenario are the behaviour
#: the attacker wants, i.e. the environment the opposite victim is attacked in.
PAPER_TABLE1: dict[tuple[str, str], dict[str, tuple[float, float]]] = {
    ("manipulation", "door-lock-v3"): {"pa-ad-oracle": (4.5, 4.0), "pa-ad": (3.5, 6.63), "sa-rl-oracle": (76.5, 14.97), "sa-rl": (39.5, 30.48), "random": (0.0, 0.0), "rat": (87.0, 10.0)},
    ("manipulation", "door-unlock-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (11.11, 13.43), "sa-rl": (0.56, 0.0), "random": (0.0, 0.0), "rat": (97.0, 6.63)},
    ("manipulation", "window-open-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (30.0, 21.19), "sa-rl": (8.0, 15.13), "random": (0.0, 0.0), "rat": (72.5, 19.62)},
    ("manipulation", "window-close-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.5, 0.0), "sa-rl-oracle": (99.0, 3.0), "sa-rl": (23.5, 37.22), "random": (0.0, 0.0), "rat": (72.5, 40.01)},
    ("manipulation", "drawer-open-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (100.0, 0.0), "sa-rl": (26.0, 27.28), "random": (0.0, 0.0), "rat": (97.5, 4.0)},
    ("manipulation", "drawer-close-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (57.5, 18.0), "sa-rl": (4.0, 8.0), "random": (0.0, 0.0), "rat": (76.0, 24.98)},
    ("manipulation", "faucet-open-v3"): {"pa-ad-oracle": (1.5, 4.0), "pa-ad": (2.5, 4.0), "sa-rl-oracle": (63.5, 20.52), "sa-rl": (0.0, 0.0), "random": (0.0, 0.0), "rat": (84.0, 21.19)},
    ("manipulation", "faucet-close-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (66.5, 16.85), "sa-rl": (4.5, 9.22), "random": (0.0, 0.0), "rat": (91.0, 6.71)},
    ("opposite", "door-lock-v3"): {"pa-ad-oracle": (9.5, 7.48), "pa-ad": (10.0, 9.17), "sa-rl-oracle": (8.0, 13.42), "sa-rl": (2.0, 0.0), "random": (1.0, 3.0), "rat": (99.0, 3.0)},
    ("opposite", "door-unlock-v3"): {"pa-ad-oracle": (3.0, 5.0), "pa-ad": (4.0, 4.58), "sa-rl-oracle": (8.0, 18.33), "sa-rl": (6.0, 12.0), "random": (0.0, 0.0), "rat": (98.5, 4.0)},
    ("opposite", "window-open-v3"): {"pa-ad-oracle": (15.5, 12.21), "pa-ad": (17.0, 11.14), "sa-rl-oracle": (15.0, 16.61), "sa-rl": (7.0, 16.12), "random": (1.0, 3.0), "rat": (77.5, 33.41)},
    ("opposite", "window-close-v3"): {"pa-ad-oracle": (38.5, 23.69), "pa-ad": (55.0, 14.7), "sa-rl-oracle": (63.0, 34.7), "sa-rl": (20.0, 39.8), "random": (5.5, 5.0), "rat": (99.0, 0.0)},
    ("opposite", "drawer-open-v3"): {"pa-ad-oracle": (1.5, 4.0), "pa-ad": (0.5, 3.0), "sa-rl-oracle": (1.11, 0.0), "sa-rl": (3.0, 0.0), "random": (0.0, 0.0), "rat": (85.5, 29.34)},
    ("opposite", "drawer-close-v3"): {"pa-ad-oracle": (88.5, 7.81), "pa-ad": (79.0, 18.44), "sa-rl-oracle": (81.0, 20.88), "sa-rl": (63.0, 32.5), "random": (0.0, 0.0), "rat": (92.0, 17.32)},
    ("opposite", "faucet-open-v3"): {"pa-ad-oracle": (6.5, 9.0), "pa-ad": (10.0, 13.75), "sa-rl-oracle": (6.0, 18.0), "sa-rl": (0.0, 0.0), "random": (0.0, 0.0), "rat": (81.5, 29.68)},
    ("opposite", "faucet-close-v3"): {"pa-ad-oracle": (19.0, 13.27), "pa-ad": (32.0, 11.0), "sa-rl-oracle": (7.0, 12.81), "sa-rl": (8.0, 16.0), "random": (0.5, 0.0), "rat": (96.0, 12.81)},
}

#: The paper's label budgets (section 5.1): 9,000 in the manipulation scenario; per task in the opposite one.
PAPER_OPPOSITE_LABELS = {"window-close-v3": 1000, "drawer-close-v3": 3000, "faucet-open-v3": 5000,
                         "faucet-close-v3": 5000, "window-open-v3": 5000, "drawer-open-v3": 7000,
                         "door-lock-v3": 7000, "door-unlock-v3": 7000}

#: The paper's table 3: average episode task reward (mean, std over 100 episodes) of each robust agent under each
#: attack, keyed by task then the robust method (the paper's ATLA-PPO and PA-ATLA are PPO agents; ours are SAC).
PAPER_TABLE3: dict[str, dict[str, dict[str, tuple[float, float]]]] = {
    "door-lock-v3": {"rat-atla": {"rat": (874, 444), "pa-ad": (628, 486), "sa-rl": (503, 120)},
                     "rat-wocar": {"rat": (774, 241), "pa-ad": (527, 512), "sa-rl": (520, 236)},
                     "pa-atla": {"rat": (491, 133), "pa-ad": (483, 15), "sa-rl": (517, 129)},
                     "atla": {"rat": (469, 11), "pa-ad": (629, 455), "sa-rl": (583, 173)}},
    "door-unlock-v3": {"rat-atla": {"rat": (477, 203), "pa-ad": (745, 75), "sa-rl": (623, 60)},
                       "rat-wocar": {"rat": (525, 78), "pa-ad": (647, 502), "sa-rl": (506, 39)},
                       "pa-atla": {"rat": (398, 12), "pa-ad": (381, 11), "sa-rl": (398, 79)},
                       "atla": {"rat": (393, 36), "pa-ad": (377, 8), "sa-rl": (385, 26)}},
    "faucet-open-v3": {"rat-atla": {"rat": (442, 167), "pa-ad": (451, 96), "sa-rl": (504, 55)},
                       "rat-wocar": {"rat": (1223, 102), "pa-ad": (1824, 413), "sa-rl": (1575, 389)},
                       "pa-atla": {"rat": (438, 53), "pa-ad": (588, 222), "sa-rl": (373, 32)},
                       "atla": {"rat": (610, 293), "pa-ad": (523, 137), "sa-rl": (495, 305)}},
    "faucet-close-v3": {"rat-atla": {"rat": (1048, 343), "pa-ad": (1223, 348), "sa-rl": (570, 453)},
                        "rat-wocar": {"rat": (1369, 158), "pa-ad": (1416, 208), "sa-rl": (3372, 1311)},
                        "pa-atla": {"rat": (661, 279), "pa-ad": (371, 65), "sa-rl": (704, 239)},
                        "atla": {"rat": (1362, 149), "pa-ad": (688, 196), "sa-rl": (426, 120)}},
}
