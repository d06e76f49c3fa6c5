"""rigctl.acquisition"""
