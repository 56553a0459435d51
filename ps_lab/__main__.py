from ps_lab.cli import main

main()
