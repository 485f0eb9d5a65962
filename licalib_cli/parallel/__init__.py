"""Using the second core: block loops shared by threads (:mod:`.threads`) and independent stages
run in a forked process (:mod:`.forked`)."""
