"""sims/so101"""
