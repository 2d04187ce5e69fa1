"""sims/obstacle2d"""
