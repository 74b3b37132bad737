"""What people look at: rerun recordings of a wagon's timeline."""
