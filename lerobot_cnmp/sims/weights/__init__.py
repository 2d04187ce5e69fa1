"""sims/weights"""
