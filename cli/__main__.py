from sonarset.cli.app import main

main()
