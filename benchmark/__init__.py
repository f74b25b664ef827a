"""The benchmark: any agent scored on fixed unseen tracks (``protocol``: the tracks, the agents a
string names, scoring, films, lap times on circuits) and the leaderboard of trained runs beside
the reference drivers (``leaderboard``). Speed measurements live in ``speed/``."""
