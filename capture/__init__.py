"""ps_lab.capture"""
