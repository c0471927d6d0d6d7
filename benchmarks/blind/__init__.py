"""The broadened blind check of the gap diagnosis (recon-bench diagnose-blind --worlds): worlds,
scenes and cases (cases), real photos with injected effects (real), evidence collection (collect),
thresholds and re-decisions (decide), leave-one-scene-out scoring and outputs (score)."""
