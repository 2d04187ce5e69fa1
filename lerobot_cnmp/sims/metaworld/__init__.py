"""sims/metaworld"""
