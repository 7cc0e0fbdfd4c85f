from icco_torchrl.cli import main

main()
