"""rigctl.simulation"""
