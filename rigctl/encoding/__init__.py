"""rigctl.encoding"""
