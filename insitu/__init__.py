"""In situ publishing: a simulation's particles to the render server (being moved from sim/)."""
