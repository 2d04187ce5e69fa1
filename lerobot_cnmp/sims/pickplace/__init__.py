"""sims/pickplace"""
