"""rigctl.storage"""
