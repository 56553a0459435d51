"""ps_lab.reconstruct"""
