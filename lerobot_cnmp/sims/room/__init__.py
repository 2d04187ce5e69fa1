"""sims/room"""
