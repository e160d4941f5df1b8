from services.deskew.service import main

main()
