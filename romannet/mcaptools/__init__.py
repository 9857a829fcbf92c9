"""`romannet mcap inspect|play|feed|export|rescore`: tools for the actor's MCAP episode files."""
