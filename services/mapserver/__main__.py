from services.mapserver.service import main

main()
