"""promp"""
