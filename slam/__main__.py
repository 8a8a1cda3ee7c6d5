from slam.cli import main

main()
