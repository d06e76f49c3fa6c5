"""rigctl.analysis"""
