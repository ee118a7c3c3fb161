"""MM-PHD-SLAM: sensor model, RBPF with GM-PHD maps per landmark type, map fusion, GOSPA.

Never imports Sionna, Mitsuba or Dr.Jit.
"""
