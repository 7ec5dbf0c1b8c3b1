"""Map-consistency metrics: PNE and CPV (plane based), the MME / MPV / MOM baselines, and RPE.

Pure numpy/scipy, no I/O; poses are 4×4 sensor-to-map matrices and every metric works in the frame of the
window's first scan (T_rel,i = T_1⁻¹ T_i).
"""
