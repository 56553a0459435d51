"""ps_lab.calibration"""
