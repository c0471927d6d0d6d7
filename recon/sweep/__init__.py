"""recon sweep: many ordinary runs (scenes, configs, seeds, withheld effects) from one sweep file.

spec reads the sweep file, trials expands it into trials with stable ids, trial runs one trial
into its own run folder, backends schedule trials (local: one after another in this process;
ray: Ray tasks), results writes the tables and summary the HTML page.
"""
